"""`citytherm compare A B -o OUT/`: the change between two surveys of the same city model.

A and B are results folders (`citytherm run`, or downloaded from the service), or with `--db`
job ids in the city model database; A is the earlier survey, the change is B − A. Writes
`OUT/change.json` and `OUT/change.gml` with ΔT textures (`workers.compare`).
"""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from db.settings import get_settings
from services.cli.db_cmd import DbUrl
from services.cli.results_cmd import database_error


def compare(
    a: str = typer.Argument(..., metavar="A", help="Earlier survey: results folder (or job id with --db)."),
    b: str = typer.Argument(..., metavar="B", help="Later survey: results folder (or job id with --db)."),
    out: Path = typer.Option(
        ..., "-o", "--out", help="Output folder (new, empty, or an earlier comparison's)."
    ),
    db: bool = typer.Option(False, "--db", help="A and B are job ids in the city model database."),
    nearest: bool = typer.Option(False, "--nearest", help="Nearest-texel re-sampling (default bilinear)."),
    database_url: str | None = DbUrl,
) -> None:
    """Per-facade change of the typical temperature (B − A) and ΔT textures where both observed."""
    from sqlalchemy.exc import SQLAlchemyError

    from workers.compare import CompareError, compare_folders
    from workers.pipeline.change import ChangeOptions

    console = Console()
    options = ChangeOptions(sampling="nearest" if nearest else "bilinear")
    columns = (TextColumn("{task.description:<24}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    try:
        with Progress(*columns, console=console, transient=True) as bars:
            task = bars.add_task("compare buildings", total=None)

            def progress(done: int, total: int) -> None:
                bars.update(task, completed=done, total=max(total, 1))

            if db:
                from workers.compare_db import compare_database_jobs

                url = database_url or get_settings().database_url
                doc = compare_database_jobs(url, a, b, out, options, progress)
            else:
                doc = compare_folders(a, b, out, options, progress)
    except (CompareError, OSError) as exc:
        console.print(f"[red]not compared:[/red] {exc}")
        raise typer.Exit(code=1) from None
    except SQLAlchemyError as exc:
        console.print(f"[red]not compared:[/red] {database_error(exc)}")
        raise typer.Exit(code=1) from None
    s = doc["summary"]
    med = s["median_delta_typical_k"]
    norm = s["median_normalised_delta_k"]
    console.print(
        f"{s['buildings']} buildings, {s['surfaces']} surfaces observed by both, {s['texels_both']:,} texels "
        f"in both; median ΔT of the typical temperature {'-' if med is None else f'{med:+.2f} K'}"
        + ("" if norm is None else f", normalised by the air temperature {norm:+.2f} K")
        + f" -> {out}"
    )


def register(root: typer.Typer) -> None:
    """Add `citytherm compare` to the root app."""
    root.command("compare")(compare)
