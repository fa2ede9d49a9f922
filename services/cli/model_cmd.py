"""`citytherm model ...`: look at and convert CityGML city models, list and delete the models of
the database.

- `citytherm model info FILE.gml` prints a summary table: CityGML version, CRS (as written and
  resolved), buildings, parts, polygons by semantic class and by LoD, and the geometry checks that
  failed (streamed: works on files of any size).
- `citytherm model convert IN.gml OUT.gml` writes the model as CityGML 2.0 (ids, appearances
  kept), optionally validating the result against the schemas.
- `citytherm model list` prints the database's city models: name, id, CRS and SRID, buildings,
  parts, state, appearance themes with their number of appearances, jobs by status (`--json`
  for scripts).
- `citytherm model delete NAME` deletes a model with its appearances, textures and jobs in one
  transaction (`db.city_models.delete_city_model`), refused while one of its jobs is accepted or
  running.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from db.citygml import CityGMLError, open_model, validate_citygml2, write_citygml
from db.citygml.checks import CheckOptions, check_building
from db.settings import get_settings
from services.cli.db_cmd import DbUrl
from services.cli.results_cmd import database_error

model_app = typer.Typer(help="Inspect and convert CityGML city models.", no_args_is_help=True)


def _crs_text(srs_name: str | None) -> str:
    if not srs_name:
        return "(none)"
    try:
        from workers.pipeline.geometry.crs import horizontal_epsg, vertical_epsg

        h, v = horizontal_epsg(srs_name), vertical_epsg(srs_name)
    except (ImportError, ValueError) as exc:
        return f"{srs_name}  [unresolved: {exc}]"
    return f"{srs_name}  [EPSG:{h}" + (f" + EPSG:{v}]" if v else "]")


@model_app.command("info")
def info(
    path: Path = typer.Argument(..., help="CityGML file (1.0, 2.0 or 3.0)."),
    checks: bool = typer.Option(True, help="Run the per-polygon geometry checks."),
    planarity_m: float = typer.Option(0.05, help="Non-planarity tolerance, metres."),
) -> None:
    """Summary of a CityGML file: version, CRS, buildings, parts, polygons, failed checks."""
    console = Console()
    try:
        header, buildings, late = open_model(path)
        n_buildings = n_parts = 0
        classes: Counter[str] = Counter()
        lods: Counter[int] = Counter()
        problems: Counter[str] = Counter()
        n_solid = n_generated = n_local_apps = 0
        themes: Counter[str] = Counter()
        opts = CheckOptions(planarity_tolerance_m=planarity_m)
        for b in buildings:
            n_buildings += 1
            for x in b.iter_buildings():
                n_parts += x.is_part
                for a in x.appearances:
                    n_local_apps += 1
                    themes[a.theme] += 1
            for p in b.iter_polygons():
                classes[p.surface_class] += 1
                lods[p.lod] += 1
                n_solid += p.in_solid
                n_generated += p.generated_id
            if checks:
                for c in check_building(b, opts):
                    problems.update(c.problems)
    except CityGMLError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=1) from None
    for a in (*header.appearances, *late):
        themes[a.theme] += 1
    table = Table(title=str(path), show_header=True)
    table.add_column("item")
    table.add_column("value", justify="right")
    table.add_row("CityGML version", header.version)
    table.add_row("CRS", _crs_text(header.srs_name))
    table.add_row("buildings", str(n_buildings))
    table.add_row("building parts", str(n_parts))
    table.add_row("polygons", str(sum(classes.values())))
    for cls, n in sorted(classes.items()):
        table.add_row(f"  {cls}", str(n))
    for lod, n in sorted(lods.items()):
        table.add_row(f"  LoD{lod}", str(n))
    table.add_row("  in a solid", str(n_solid))
    table.add_row("  with generated id", str(n_generated))
    table.add_row("appearance themes", ", ".join(f"{t} ({n})" for t, n in themes.items()) or "-")
    if checks:
        table.add_row("failed checks", str(sum(problems.values())) if problems else "none")
        for name, n in sorted(problems.items()):
            table.add_row(f"  {name}", str(n))
    console.print(table)


@model_app.command("convert")
def convert(
    src: Path = typer.Argument(..., help="Input CityGML file (1.0, 2.0 or 3.0)."),
    dst: Path = typer.Argument(..., help="Output CityGML 2.0 file."),
    validate: bool = typer.Option(False, help="Validate the output against the CityGML 2.0 schemas."),
) -> None:
    """Write a CityGML model as CityGML 2.0 (streamed; ids and appearances kept)."""
    console = Console()
    try:
        header, buildings, late = open_model(src)
        n = write_citygml(
            dst,
            buildings,
            srs_name=header.srs_name,
            envelope=header.envelope,
            model_appearances=header.appearances,
            name=header.name,
            trailing_appearances=late,
        )
    except CityGMLError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=1) from None
    console.print(f"wrote {n} buildings to {dst} (CityGML 2.0)")
    if validate:
        errors = validate_citygml2(dst)
        if errors:
            for e in errors[:20]:
                console.print(f"[red]invalid:[/red] {e}")
            raise typer.Exit(code=2)
        console.print("valid against the CityGML 2.0 schemas")


def _counts(counts: dict[str, int]) -> str:
    """`{"a": 2, "b": 1}` -> `a (2), b (1)`."""
    return ", ".join(f"{k} ({n})" for k, n in counts.items()) or "none"


@model_app.command("list")
def list_cmd(
    as_json: bool = typer.Option(False, "--json", help="Print the list as JSON."),
    database_url: str | None = DbUrl,
) -> None:
    """The city models of the database with their appearance themes and jobs."""
    import json

    from sqlalchemy.exc import SQLAlchemyError

    from db.city_models import list_models

    console = Console()
    try:
        models = list_models(database_url or get_settings().database_url)
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/red] {database_error(exc)}")
        raise typer.Exit(code=1) from None
    if as_json:
        doc = [
            {
                "name": m.name,
                "id": m.id,
                "srs_name": m.srs_name,
                "srid": m.srid,
                "buildings": m.buildings,
                "parts": m.parts,
                "surfaces": m.surfaces,
                "state": m.state,
                "imported_at": m.imported_at.isoformat() if m.imported_at is not None else None,
                "themes": m.themes,
                "jobs": m.jobs,
            }
            for m in models
        ]
        typer.echo(json.dumps(doc, indent=1))
        return
    # one block per model: readable in a terminal of any width, however many themes
    if not models:
        console.print("no city models in the database")
    for m in models:
        crs = f"{m.srs_name or '(none)'} (SRID {m.srid})"
        console.print(f"[bold]{m.name}[/bold]  id {m.id}, {m.state}, CRS {crs}")
        console.print(f"  {m.buildings} buildings, {m.parts} parts, {m.surfaces} surfaces")
        console.print(f"  themes: {_counts(m.themes)}")
        console.print(f"  jobs: {_counts(m.jobs)}")


@model_app.command("delete")
def delete_cmd(
    name: str = typer.Argument(..., help="Model name (or id)."),
    yes: bool = typer.Option(False, "--yes", "-y", help="Do not ask for confirmation."),
    database_url: str | None = DbUrl,
) -> None:
    """Delete a city model of the database with its appearances, textures and jobs (refused while
    one of its jobs is accepted or running)."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.city_models import delete_city_model
    from db.errors import CityDBError

    console = Console()
    if not yes:
        typer.confirm(f"delete city model {name!r} with its appearances, textures and jobs?", abort=True)
    try:
        d = delete_city_model(database_url or get_settings().database_url, name)
    except CityDBError as exc:
        console.print(f"[red]not deleted:[/red] {exc}")
        raise typer.Exit(code=1) from None
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/red] {database_error(exc)}")
        raise typer.Exit(code=1) from None
    console.print(
        f"deleted city model [bold]{d.name}[/bold] (id {d.id}): {d.buildings} buildings, "
        f"{d.appearances} appearances, {d.images} texture images, {d.jobs} jobs in {d.seconds:.1f} s"
    )


def register(root: typer.Typer) -> None:
    """Add the `model` command group to the root app."""
    root.add_typer(model_app, name="model")
