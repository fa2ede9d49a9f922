"""Database commands: `citytherm db upgrade|downgrade|current|repair`, `citytherm import CITY.gml`,
`citytherm export --model M -o OUT/`.

The database is `CITYTHERM_DATABASE_URL` (settings) unless `--database-url` is given.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from rich.console import Console

from db.settings import get_settings

console = Console()
err_console = Console(stderr=True)
db_app = typer.Typer(help="City model database: schema (Alembic migrations), repair.", no_args_is_help=True)


def _url(database_url: str | None) -> str:
    return database_url or get_settings().database_url


DbUrl = typer.Option(None, "--database-url", help="SQLAlchemy/libpq URL (default: CITYTHERM_DATABASE_URL).")


@db_app.command("upgrade")
def upgrade_cmd(
    revision: str = typer.Argument("head"),
    srid: int | None = typer.Option(
        None,
        "--srid",
        help="EPSG code of the geometry columns when the schema is created (default: "
        "CITYTHERM_DATABASE_SRID, 25832); a typed database keeps its SRID",
    ),
    database_url: str | None = DbUrl,
) -> None:
    """Upgrade the schema to REVISION (default: the newest)."""
    from db.migrations import current_revision, upgrade

    url = _url(database_url)
    upgrade(url, revision, srid=srid if srid is not None else get_settings().database_srid)
    console.print(f"database at revision [bold]{current_revision(url)}[/bold]")


@db_app.command("downgrade")
def downgrade_cmd(revision: str = typer.Argument(..., help="target revision, e.g. 'base' or '-1'"),
                  database_url: str | None = DbUrl) -> None:  # fmt: skip
    """Downgrade the schema to REVISION ('base' drops every citytherm table and view)."""
    from db.migrations import current_revision, downgrade

    url = _url(database_url)
    downgrade(url, revision)
    console.print(f"database at revision [bold]{current_revision(url)}[/bold]")


@db_app.command("current")
def current_cmd(database_url: str | None = DbUrl) -> None:
    """Print the schema revision of the database and the newest one available."""
    from db.migrations import current_revision, head_revision

    console.print(f"current: {current_revision(_url(database_url))}  head: {head_revision()}")


@db_app.command("repair")
def repair_cmd(
    dry_run: bool = typer.Option(False, "--dry-run", help="only report what would be repaired"),
    database_url: str | None = DbUrl,
) -> None:
    """Remove city models left 'importing' by imports that died, rebuild missing or invalid spatial
    indexes (concurrently: the tables stay usable); report what was found and done."""
    from db.ops import ensure_spatial_indexes, remove_dead_imports, running_imports
    from db.session import make_engine

    engine = make_engine(_url(database_url))
    try:
        models = remove_dead_imports(engine, dry_run=dry_run)
        indexes = ensure_spatial_indexes(engine, dry_run=dry_run)
        running = running_imports(engine)
    finally:
        engine.dispose()
    for pid, name, state, since in running:
        console.print(f"import of [bold]{name}[/bold] running (backend pid {pid}, {state}, since {since})")
    for m in models:
        what = {"removed": "removed", "dead": "would remove", "in progress": "left alone (import running)"}
        console.print(
            f"model [bold]{m.name}[/bold] (id {m.model_id}, 'importing'): {what[m.status]}"
            + (
                ""
                if m.status == "in progress"
                else f" ({m.buildings} buildings, {m.parts} parts, {m.surfaces} surfaces)"
            )
        )
    for i in indexes:
        action = "rebuilt" if i.rebuilt else "would rebuild"
        console.print(f"spatial index [bold]{i.name}[/bold] on {i.table}({i.column}) {i.problem}: {action}")
    if not models and not indexes:
        console.print("nothing to repair: no dead imports, spatial indexes in place")


def _rates(buildings: int, parts: int, seconds: float) -> str:
    if seconds <= 0:
        return ""
    return f" ({buildings / seconds:.0f} buildings/s, {parts / seconds:.0f} parts/s)"


def import_cmd(
    city_gml: Path = typer.Argument(..., exists=True, dir_okay=False, help="CityGML file (1.0, 2.0 or 3.0)"),
    name: str | None = typer.Option(None, "--name", help="model name (default: the file's stem)"),
    replace: bool = typer.Option(False, "--replace", help="replace an existing model of that name"),
    checks: str = typer.Option("fast", "--checks", help="geometry checks: fast, full or none"),
    progress: bool = typer.Option(False, "--progress", help="print progress lines on stderr"),
    crs: str | None = typer.Option(
        None, "--crs", help="CRS of the file's coordinates (e.g. EPSG:25832) when it names none, or instead"
    ),
    database_url: str | None = DbUrl,
) -> None:
    """Import a CityGML file into the city model database (streamed; all or nothing: an error,
    Ctrl-C, SIGTERM or a killed process leaves nothing behind). Geometries are stored in the
    database SRID (transformed when the model's CRS is another; heights kept)."""
    from db.import_options import ImportOptions
    from db.import_stream import prestart

    options = ImportOptions(checks=checks, crs=crs)
    # the reader processes of a large file start first: they load their modules and parse while
    # this process loads the database layer (import_citygml owns and closes them)
    readers = prestart(city_gml, options)
    try:
        from db.errors import CityDBError
        from db.importer import ImportInterrupted, ImportProgress, import_citygml
    except BaseException:
        if readers is not None:
            readers.close()
        raise

    def show(p: ImportProgress) -> None:
        print(
            f"progress: {p.stage} {p.buildings} buildings {p.parts} parts {p.surfaces} surfaces "
            f"{p.seconds:.1f} s{_rates(p.buildings, p.parts, p.seconds)}",
            file=sys.stderr,
            flush=True,
        )

    try:
        s = import_citygml(
            _url(database_url),
            city_gml,
            name=name,
            replace=replace,
            options=options,
            progress=show if progress else None,
            readers=readers,
        )
    except ImportInterrupted as exc:
        err_console.print(f"[red]import stopped:[/red] {exc}")
        raise typer.Exit(128 + exc.signum) from None
    except (CityDBError, ValueError) as exc:
        console.print(f"[red]import failed:[/red] {exc}")
        raise typer.Exit(1) from exc
    console.print(
        f"model [bold]{s.name}[/bold] (id {s.model_id}, EPSG:{s.srid}{', replaced' if s.replaced else ''}): "
        f"{s.buildings} buildings, {s.parts} parts, {s.surfaces} surfaces, {s.appearances} appearances "
        f"in {s.seconds:.1f} s{_rates(s.buildings, s.parts, s.seconds)}"
    )


def _bbox(value: str | None) -> tuple[float, float, float, float] | None:
    if value is None:
        return None
    try:
        parts = tuple(float(v) for v in value.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 4 or parts[0] > parts[2] or parts[1] > parts[3]:
        raise typer.BadParameter("--bbox must be minx,miny,maxx,maxy (model CRS)")
    return parts  # type: ignore[return-value]


def export_cmd(
    model: str | None = typer.Option(None, "--model", help="model name or id"),
    out: Path = typer.Option(..., "-o", "--out", help="output folder (textured.gml, textures/)"),
    theme: str | None = typer.Option(None, "--theme", help="only this appearance theme"),
    job: str | None = typer.Option(None, "--job", help="only this job's appearances"),
    bbox: str | None = typer.Option(None, "--bbox", help="minx,miny,maxx,maxy in the model CRS"),
    database_url: str | None = DbUrl,
    fmt: str = typer.Option("citygml", "--format", help="citygml, or 3dtiles (docs/3dtiles.md)"),
    results: Path | None = typer.Argument(None, help="3dtiles: a results folder instead of --model"),
    range_c: str | None = typer.Option(None, "--range-c", help="3dtiles: colour range LO,HI in °C"),
    geoid_m: float | None = typer.Option(None, "--geoid-undulation", help="3dtiles: added to heights, m"),
    max_buildings: int = typer.Option(50, "--max-buildings", min=1, help="3dtiles: buildings per tile"),
    workers: int = typer.Option(1, "--workers", min=1, help="3dtiles: processes writing tiles"),
) -> None:
    """Export a city model as CityGML 2.0 plus texture files (the results format), or with
    `--format 3dtiles` a results folder or a model's newest job as 3D Tiles 1.1."""
    from db.errors import CityDBError
    from db.export import export_citygml

    if fmt == "3dtiles":
        from services.cli.tiles3d_cmd import export_3dtiles_cmd

        return export_3dtiles_cmd(results, out, model=model, job=job, theme=theme, range_c=range_c,
                                  geoid_undulation_m=geoid_m, max_buildings=max_buildings,
                                  workers=workers, database_url=database_url)  # fmt: skip
    if fmt != "citygml" or model is None or results is not None:
        raise typer.BadParameter("--format citygml exports --model M (a folder needs --format 3dtiles)")
    try:
        s = export_citygml(_url(database_url), out, model=model, theme=theme, job_id=job, bbox=_bbox(bbox))
    except CityDBError as exc:
        console.print(f"[red]export failed:[/red] {exc}")
        raise typer.Exit(1) from exc
    console.print(
        f"wrote {s.path} ({s.buildings} buildings, {s.textures} textures, {s.anomalies} anomalies) "
        f"in {s.seconds:.1f} s"
    )


def register(root: typer.Typer) -> None:
    """Add `db`, `import` and `export` to the root app."""
    root.add_typer(db_app, name="db")
    root.command("import")(import_cmd)
    root.command("export")(export_cmd)
