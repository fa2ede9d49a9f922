"""`citytherm model ...`: look at and convert CityGML city models.

- `citytherm model info FILE.gml` prints a summary table: CityGML version, CRS (as written and
  resolved), buildings, parts, polygons by semantic class and by LoD, and the geometry checks that
  failed (streamed: works on files of any size).
- `citytherm model convert IN.gml OUT.gml` writes the model as CityGML 2.0 (ids, appearances
  kept), optionally validating the result against the schemas.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from db.citygml import CityGMLError, open_model, validate_citygml2, write_citygml
from db.citygml.checks import CheckOptions, check_building

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


def register(root: typer.Typer) -> None:
    """Add the `model` command group to the root app."""
    root.add_typer(model_app, name="model")
