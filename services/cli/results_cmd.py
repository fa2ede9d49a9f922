"""`citytherm results import RESULTS/ --model NAME`: a results folder made earlier (by
`citytherm run`, or downloaded from the service) into the city model database.

Every building of the folder goes into the model in one transaction each, with its textures,
appearance, statistics, poses and anomalies, under one job whose id follows from the model and
the folder (`db.results_import`): importing the same folder again replaces that job's rows. A
folder whose buildings are not in the model is refused, and nothing is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from db.settings import get_settings
from services.cli.db_cmd import DbUrl

if TYPE_CHECKING:
    from db.results_import import ResultsImportSummary

results_app = typer.Typer(help="Results folders and the city model database.", no_args_is_help=True)


def database_error(exc: BaseException) -> str:
    """A database error in one line (the driver's message, without SQLAlchemy's SQL dump)."""
    orig = getattr(exc, "orig", None) or exc
    return f"database: {type(orig).__name__}: {' '.join(str(orig).split())}"


def import_with_progress(
    database_url: str, folder: Path, model: str | int, console: Console, job: str | None = None
) -> ResultsImportSummary:
    """`db.results_import.import_results` with a progress bar; returns its summary."""
    from db.results_import import import_results

    columns = (TextColumn("{task.description:<30}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console, transient=False) as bars:
        task = bars.add_task("store buildings in the database", total=None)

        def progress(done: int, total: int) -> None:
            bars.update(task, completed=done, total=max(total, 1))

        return import_results(database_url, folder, model=model, job_id=job, progress=progress)


def summary_line(s: ResultsImportSummary) -> str:
    """One line on a `ResultsImportSummary`."""
    rate = s.seconds / s.buildings if s.buildings else 0.0
    extra = f", {s.failed} failed" if s.failed else ""
    extra += f", {s.removed} of an earlier import removed" if s.removed else ""
    return (
        f"city model [bold]{s.model}[/bold] (id {s.model_id}), job {s.job_id} "
        f"({'new' if s.created else 'replaced'}, {s.status}): {s.buildings} buildings{extra}; "
        f"{s.images} textures, {s.surfaces} surface statistics, {s.poses} poses, {s.anomalies} anomalies "
        f"in {s.seconds:.1f} s ({rate:.2f} s per building)"
    )


@results_app.command("import")
def import_cmd(
    folder: Path = typer.Argument(..., help="Results folder (textured.gml, textures/, report.json, ...)."),
    model: str | None = typer.Option(
        None,
        "--model",
        help="City model name (or id) the results belong to (default: the stem of the city model file "
        "named in report.json, as `citytherm import` names it).",
    ),
    job: str | None = typer.Option(
        None, "--job", help="Job id to store under (default: derived from the model and the folder)."
    ),
    database_url: str | None = DbUrl,
) -> None:
    """Put a results folder made earlier into the city model database."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.errors import CityDBError

    console = Console()
    if model is None:
        model = _model_of_report(folder, console)
    try:
        url = database_url or get_settings().database_url
        summary = import_with_progress(url, folder, model, console, job)
    except (CityDBError, ValueError, OSError) as exc:
        console.print(f"[red]not imported:[/red] {exc}")
        raise typer.Exit(code=1) from None
    except SQLAlchemyError as exc:
        console.print(f"[red]not imported:[/red] {database_error(exc)}")
        raise typer.Exit(code=1) from None
    console.print(summary_line(summary))


def _model_of_report(folder: Path, console: Console) -> str:
    """The default model name: the stem of `report.json`'s `city_model`."""
    import json

    try:
        city = json.loads((folder / "report.json").read_text(encoding="utf-8"))["city_model"]
        return Path(str(city)).stem
    except (OSError, ValueError, KeyError, TypeError) as exc:
        where = folder / "report.json"
        console.print(f"[red]not imported:[/red] {where}: no city model named ({exc!r}); give --model")
        raise typer.Exit(code=1) from None


def register(root: typer.Typer) -> None:
    """Add the `results` command group to the root app."""
    root.add_typer(results_app, name="results")
