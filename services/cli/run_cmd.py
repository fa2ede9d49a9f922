"""`citytherm run CITY.gml PACKAGE -o OUT/`: a whole texturing job in one process (or a local
process pool), with a progress bar per stage and a closing summary table.

With `--database` the results also go into the city model database, into the model `--model`
(default: the file's stem, as `citytherm import` names it; imported first when the database lacks
it, before the job runs). They are stored once the results folder is complete, by the same
function as `citytherm results import OUT/` (`db.results_import.import_results`: one transaction
per building, a job id derived from the model and the folder), so both give the same rows and a
re-run replaces them."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from db.settings import get_settings
from services.cli.db_cmd import DbUrl
from services.cli.results_cmd import database_error, import_with_progress, summary_line
from workers.job import RunError, RunOptions
from workers.run import RunSummary, run_job

#: the library's defaults are the command line's
_DEFAULTS = RunOptions()


class Orientation(StrEnum):
    """`--orientation`: `RunOptions.orientation`."""

    edges = "edges"
    sfm = "sfm"
    both = "both"

_LABELS = {
    "ingest": "read model and package",
    "calibrate": "calibrate the sequence",
    "orient": "orient the sequence",
    "plan": "plan building units",
    "units": "orient and texture buildings",
    "write": "write results",
    "split_half": "split-half check",
}


def summary_table(summary: RunSummary, limit: int = 30) -> Table:
    """Rich table: one row per processed building (the `limit` with most texels) and a total row.

    `cover` is the observed share of the texels of the surfaces that got any texel (surfaces the
    sequence never saw, e.g. back walls, are not counted)."""
    table = Table(title=f"citytherm run: {summary.out_dir}", show_footer=False)
    for col, justify in (
        ("building", "left"),
        ("frames", "right"),
        ("surfaces", "right"),
        ("texels", "right"),
        ("cover", "right"),
        ("m/px", "right"),
        ("tiles", "right"),
        ("refined", "right"),
    ):
        table.add_column(col, justify=justify, no_wrap=col != "building")  # type: ignore[arg-type]
    rows = sorted(summary.results, key=lambda r: -sum(s.texels_observed for s in r.surfaces))
    for r in rows[:limit]:
        obs = sum(s.texels_observed for s in r.surfaces)
        tot = sum(s.texels_total for s in r.surfaces if s.texels_observed)
        res = [s.mean_resolution_m for s in r.surfaces if s.texels_observed]
        table.add_row(
            r.building_id if len(r.building_id) <= 24 else "…" + r.building_id[-23:],
            str(summary.units_frames.get(r.building_id, 0)),
            f"{sum(1 for s in r.surfaces if s.texels_observed)}/{len(r.surfaces)}",
            f"{obs:,}",
            f"{obs / tot:.0%}" if tot else "-",
            f"{sum(res) / len(res):.3f}" if res else "-",
            str(sum(1 for _ in (r.appearance.surface_data if r.appearance else ()))),
            f"{sum(1 for p in r.poses if p.status == 'refined')}/{len(r.poses)}" if r.poses else "-",
        )
    if len(rows) > limit:
        table.add_row(f"... {len(rows) - limit} more", "", "", "", "", "", "", "")
    tot = sum(s.texels_total for r in summary.results for s in r.surfaces if s.texels_observed)
    table.add_row(
        f"[bold]total: {len(rows)}[/]",
        str(summary.n_frames),
        "",
        f"[bold]{summary.texels_observed:,}[/]",
        f"{summary.texels_observed / tot:.0%}" if tot else "-",
        "",
        "",
        "on" if summary.refine else "off",
    )
    return table


def anomalies_line(summary: RunSummary) -> str:
    """One line on the thermal analysis: leak candidates, windows and bridges found."""
    kinds = [a.kind for r in summary.results for a in r.anomalies]
    return (
        f"thermal anomalies: {kinds.count('leak')} leak candidates, {kinds.count('window')} windows, "
        f"{kinds.count('bridge')} thermal bridges (anomalies.geojson)"
    )


def run_with_progress(
    city: Path, package: Path, out: Path, options: RunOptions, console: Console
) -> RunSummary:
    """`run_job` with one rich progress bar per stage."""
    columns = (
        TextColumn("{task.description:<30}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=False) as bars:
        # a bar per stage that runs, made when the stage first reports (calibrate and orient run
        # only with refinement, orient only for close-range sequences)
        tasks: dict[str, Any] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bars.add_task(_LABELS.get(stage, stage), total=None)
            bars.update(tasks[stage], completed=done, total=max(total, 1))

        return run_job(city, package, out, options, progress)


def run(
    city: Path = typer.Argument(..., help="CityGML file (1.0, 2.0 or 3.0)."),
    package: Path = typer.Argument(..., help="Sequence package: folder, sequence.json, .zip or .tar(.gz)."),
    out: Path = typer.Option(..., "-o", "--out", help="Results folder (created)."),
    resolution: float = typer.Option(
        _DEFAULTS.resolution_px_per_m, "--resolution", help="Texels per metre on every surface."
    ),
    theme: str = typer.Option(_DEFAULTS.theme, "--theme", help="Appearance theme of the textures."),
    buildings: str | None = typer.Option(None, "--buildings", help="Comma-separated building ids."),
    workers: int = typer.Option(
        _DEFAULTS.workers, "--workers", min=1, help="Processes for the building units."
    ),
    no_refine: bool = typer.Option(False, "--no-refine", help="Keep the GNSS/INS prior poses."),
    no_calibrate: bool = typer.Option(
        False,
        "--no-calibrate",
        help="With refinement: skip the sequence calibration (boresight, GNSS offset, lever arm, "
        "time delay) and refine each building from the raw priors.",
    ),
    no_orient: bool = typer.Option(
        False,
        "--no-orient",
        help="With refinement: skip the sequence orientation of drives, terrestrial sequences and flights "
        "(feature tracks and a block adjustment of all frames with the model before the buildings).",
    ),
    orientation: Orientation = typer.Option(
        Orientation(_DEFAULTS.orientation),
        "--orientation",
        help="With the sequence orientation: edges = blocks with model edges and planes; sfm = the "
        "sequence's own pycolmap reconstruction placed on the GNSS/INS and coregistered to the "
        "facades; both = edges where confirmed, the reconstruction for the frames they leave.",
    ),
    rgb: bool = typer.Option(
        False,
        "--rgb",
        help="With the sequence orientation: first register the TIR block onto the dense cloud of "
        "the package's RGB camera (rgb_camera; Hoegner & Stilla's method 3; about 2 CPU minutes "
        "per 50 frames). report.json: sequence_orientation.rgb.",
    ),
    no_display: bool = typer.Option(False, "--no-display", help="Skip the 8-bit <theme>-display copies."),
    no_anomalies: bool = typer.Option(
        False,
        "--no-anomalies",
        help="Skip the thermal analysis (windows, heat-leak candidates, facade figures; "
        "anomalies.geojson is then not written).",
    ),
    split_half: bool = typer.Option(
        False,
        "--split-half",
        help="Also texture each building's even and odd frames separately and report in report.json "
        "how the two halves agree (tile shifts, value differences): texture quality without ground "
        "truth. The results stay the same.",
    ),
    database: bool = typer.Option(
        False,
        "--database",
        help="Also store the results in the city model database (one transaction per building).",
    ),
    model: str | None = typer.Option(
        None,
        "--model",
        help="With --database: the city model (default: CITY's file stem; imported first if missing).",
    ),
    database_url: str | None = DbUrl,
) -> None:
    """Texture every building the sequence sees and write the results folder (and with
    --database store it in the city model database)."""
    console = Console()
    if model is not None and not database:
        console.print("[red]error:[/] --model needs --database")
        raise typer.Exit(code=2)
    url = database_url or get_settings().database_url
    model_id = _database_model(url, city, model, console) if database else None
    ids = tuple(b.strip() for b in buildings.split(",") if b.strip()) if buildings else None
    options = RunOptions.build(
        resolution_px_per_m=resolution,
        theme=theme,
        refine=False if no_refine else None,  # None: the library's default (on)
        anomalies=False if no_anomalies else None,
        buildings=ids,
        workers=workers,
        calibrate=not no_calibrate,
        orient=not no_orient,
        orientation=orientation.value,
        rgb=rgb,
        display=not no_display,
        split_half=split_half,
    )
    try:
        summary = run_with_progress(city, package, out, options, console)
    except (RunError, ValueError, OSError) as exc:
        console.print(f"[red]error:[/] {exc}")
        raise typer.Exit(code=2) from exc
    console.print(summary_table(summary))
    if summary.warning:
        console.print(f"[yellow]warning:[/] {summary.warning}")
    for f in summary.failures:
        console.print(f"[red]failed:[/] building {f.building_id}: {f.error}")
    t = summary.timings_s
    console.print(
        "stage times: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in t.items())
        + f"; results in {summary.out_dir}"
    )
    if options.unit.anomalies.enabled:
        console.print(anomalies_line(summary))
    if not options.refine:
        console.print("poses: GNSS/INS priors (refinement off)")
    elif summary.calibration is not None:
        console.print(calibration_line(summary.calibration))
        if summary.orientation and summary.orientation.get("run"):
            console.print(orientation_line(summary.orientation))
    if summary.split_half is not None:
        console.print(split_half_line(summary.split_half))
    if model_id is not None:
        _store(url, out, model_id, console)


def _database_model(url: str, city: Path, model: str | None, console: Console) -> int:
    """The id of the city model the results go into, imported from `city` first when missing
    (before the job runs, so that a database that cannot take them fails early)."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.errors import CityDBError
    from db.results_import import ensure_model

    try:
        m, imported = ensure_model(url, city, model)
    except (CityDBError, ValueError, OSError) as exc:
        console.print(f"[red]error:[/] city model for the database: {exc}")
        raise typer.Exit(code=1) from None
    except SQLAlchemyError as exc:
        console.print(f"[red]error:[/] {database_error(exc)}")
        raise typer.Exit(code=1) from None
    if imported is not None:
        console.print(
            f"imported {city} as city model [bold]{imported.name}[/bold] (id {imported.model_id}): "
            f"{imported.buildings} buildings, {imported.parts} parts in {imported.seconds:.1f} s"
        )
    return int(m["id"])


def _store(url: str, out: Path, model_id: int, console: Console) -> None:
    """The finished results folder into the database (`citytherm results import`)."""
    from sqlalchemy.exc import SQLAlchemyError

    from db.errors import CityDBError

    try:
        s = import_with_progress(url, out, model_id, console)
    except (CityDBError, ValueError, OSError) as exc:
        console.print(f"[red]not stored in the database:[/] {exc} (the results are in {out})")
        raise typer.Exit(code=1) from None
    except SQLAlchemyError as exc:
        console.print(f"[red]not stored in the database:[/] {database_error(exc)} (the results are in {out})")
        raise typer.Exit(code=1) from None
    console.print(summary_line(s))


def calibration_line(cal: dict[str, Any]) -> str:
    """One line on the sequence calibration of report.json (`calibration` block)."""
    if not cal.get("run"):
        return "calibration: off"
    if not cal.get("accepted"):
        return f"calibration: not accepted ({cal.get('reason', '')}); units refine from the priors"
    b = ", ".join(f"{v:+.2f}" for v in cal.get("boresight_correction_deg", []))
    o = ", ".join(f"{v:+.2f}" for v in cal.get("gnss_offset_m", []))
    return (
        f"calibration: boresight correction [{b}] deg, GNSS offset [{o}] m, "
        f"time delay {cal.get('time_delay_s', 0.0):+.3f} s, {cal.get('frames', 0)} frames, "
        f"edge support {cal.get('mean_edge_support', 0.0):.2f}"
    )


def orientation_line(doc: dict[str, Any]) -> str:
    """One line on the sequence orientation of report.json (`sequence_orientation` block)."""
    blocks = doc.get("blocks", [])
    ok = sum(1 for b in blocks if b.get("accepted"))
    return (f"sequence orientation: {doc.get('frames_oriented', 0)} of {doc.get('frames', 0)} frames "
            f"oriented in {ok} of {len(blocks)} blocks")


def split_half_line(doc: dict[str, Any]) -> str:
    """One line on the split-half check of report.json (`split_half` block)."""
    if not doc.get("tiles"):
        return (f"split half: no tile both halves observe with contrast; median |ΔT| "
                f"{doc.get('median_abs_diff_k')} over {doc.get('texels_common', 0)} texels")
    return (
        f"split half: median tile shift {doc['median_shift_texels']:.2f} texel "
        f"({doc['median_shift_m'] * 1000:.1f} mm), {doc['tiles_agreeing']} of {doc['tiles']} tiles agree, "
        f"median |ΔT| {doc['median_abs_diff_k']:.3f}, RMS {doc['rms_diff_k']:.3f}"
    )


def register(root: typer.Typer) -> None:
    """Add `citytherm run` to the root app."""
    root.command("run")(run)
