"""`citytherm export --format 3dtiles`: a textured model as 3D Tiles 1.1 (docs/3dtiles.md).

- `citytherm export --format 3dtiles RESULTS/ -o OUT/`: a results folder (`citytherm run`);
- `citytherm export --format 3dtiles --model M [--job J] -o OUT/`: a model's newest job (or job
  J) from the database.

The work is `db.tiles3d`; this module parses the options and prints the summary.
"""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console

from db.settings import get_settings

console = Console()


def _range(value: str | None) -> tuple[float, float] | None:
    """`--range-c LO,HI` (°C) -> kelvin."""
    if value is None:
        return None
    try:
        lo, hi = (float(v) for v in value.split(","))
    except ValueError:
        raise typer.BadParameter("--range-c must be LO,HI in °C, e.g. -5,25") from None
    if not lo < hi:
        raise typer.BadParameter("--range-c: LO must be below HI")
    return lo + 273.15, hi + 273.15


def export_3dtiles_cmd(
    results: Path | None,
    out: Path,
    *,
    model: str | None,
    job: str | None,
    theme: str | None,
    range_c: str | None,
    geoid_undulation_m: float | None,
    max_buildings: int,
    database_url: str | None,
    workers: int = 1,
) -> None:
    """Export a results folder or a database model as a 3D Tiles tileset into `out`."""
    from db.errors import CityDBError
    from db.tiles3d import SourceError, TilesOptions, export_3dtiles, folder_source
    from db.tiles3d.database import export_model_3dtiles

    opts = TilesOptions(
        max_buildings=max_buildings,
        display_range=_range(range_c),
        geoid_undulation_m=geoid_undulation_m,
        workers=workers,
    )
    try:
        if results is not None:
            s = export_3dtiles(folder_source(results, theme), out, opts)
        elif model is not None:
            url = database_url or get_settings().database_url
            s = export_model_3dtiles(url, out, model=model, job_id=job, options=opts)
        else:
            raise typer.BadParameter("give a results folder, or --model for a model of the database")
    except (SourceError, CityDBError, ValueError, OSError) as exc:
        console.print(f"[red]export failed:[/red] {exc}")
        raise typer.Exit(1) from exc
    rate = s.buildings / s.seconds if s.seconds > 0 else 0.0
    console.print(
        f"wrote {s.path} ({s.buildings} buildings, {s.tiles} tiles, {s.surfaces} surfaces, "
        f"{s.triangles} triangles, {s.images} textures, {s.bytes / 1e6:.1f} MB) in {s.seconds:.1f} s "
        f"({rate:.0f} buildings/s); colours: {s.display.colormap} "
        f"{s.display.lo:.2f}..{s.display.hi:.2f} {s.unit}"
    )
    if not s.exact_heights:
        console.print(
            "[yellow]heights:[/yellow] PROJ has no geoid grid for the model's height system here: heights "
            "are taken as ellipsoidal (give --geoid-undulation M, or install the grid; docs/3dtiles.md)"
        )
