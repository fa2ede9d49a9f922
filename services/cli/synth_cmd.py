"""`citytherm synth`: render a synthetic TIR sequence package with ground truth.

    citytherm synth --model M.gml --platform drive --buildings 5 --frames 100 --seed 1 \\
        --truth TRUTH.json -o PACKAGE/ [--rgb] [--occluders]

Without `--model` the bundled Berlin LoD2 model is used (`--procedural N` builds a block of N
gable-roofed houses instead). `--rgb` adds a visible-band camera on the same mount (frames
`rgb/NNNNNN.png`, the manifest's `rgb_camera` section). `--occluders` renders street trees and
parked cars that the model lacks (`synth.occluders`; listed in the truth). The truth file (true
poses, mounting, delay, anomalies; see `docs/synth-truth.md`) is written next to the package,
never inside it.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from db.sequence_package import PackageError
from db.synth_files import write_synthetic_package
from workers.pipeline.synth import (
    BUNDLED_MODEL,
    DriveOptions,
    ErrorOptions,
    FlightOptions,
    OccluderOptions,
    RgbOptions,
    SensorOptions,
    SynthError,
    SynthOptions,
    ThermalOptions,
    default_camera,
    procedural_block,
    synthesize,
)
from workers.pipeline.synth.trajectory import TerrestrialOptions


def _triple(text: str | None, name: str) -> tuple[float, float, float] | None:
    """`"a,b,c"` -> `(a, b, c)`; None stays None; a clear error naming the option otherwise."""
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"{name}: expected three comma-separated numbers, got {text!r}") from None
    if len(vals) != 3:
        raise typer.BadParameter(f"{name}: expected three comma-separated numbers, got {text!r}")
    return vals  # type: ignore[return-value]


def _cluster(text: str) -> int | tuple[str, ...]:
    """`--buildings`: a count (`"5"`) or comma-separated building ids."""
    t = text.strip()
    if t.isdigit():
        return int(t)
    ids = tuple(i.strip() for i in t.split(",") if i.strip())
    if not ids:
        raise typer.BadParameter("--buildings: give a count or comma-separated building ids")
    return ids


class _Progress:
    """Iterate a `SynthFrames` while advancing a rich progress bar."""

    def __init__(self, frames: object, progress: Progress, task: int) -> None:
        self.frames, self.progress, self.task = frames, progress, task

    def __iter__(self) -> Iterator:
        for f in self.frames:  # type: ignore[attr-defined]
            yield f
            self.progress.advance(self.task)


def synth(
    out: Path = typer.Option(..., "-o", "--out", help="Package folder to write."),
    model: Path | None = typer.Option(None, "--model", help="CityGML model (default: bundled Berlin LoD2)."),
    procedural: int = typer.Option(0, "--procedural", help="Use a procedural block of N houses instead."),
    platform: str = typer.Option(
        "drive", "--platform", help="drive, flight or terrestrial (a hand-held camera along one facade)."
    ),
    buildings: str = typer.Option("5", "--buildings", help="Cluster: a count or comma-separated ids."),
    frames: int = typer.Option(100, "--frames", help="Number of frames."),
    seed: int = typer.Option(0, "--seed", help="Seed of everything random."),
    truth: Path | None = typer.Option(None, "--truth", help="Truth file (default: <out>.truth.json)."),
    interval: float = typer.Option(0.1, "--interval", help="Seconds between frames."),
    speed: float | None = typer.Option(None, "--speed", help="m/s (default 8 drive, 20 flight)."),
    height: float | None = typer.Option(None, "--height", help="m above ground (default 2.25 / 200)."),
    distance: float = typer.Option(
        11.0, "--distance", help="Drive / terrestrial: metres from the facades (8-15; terrestrial 10)."
    ),
    pattern: str = typer.Option("circle", "--pattern", help="Flight: circle or strips."),
    no_errors: bool = typer.Option(False, "--no-errors", help="Error-free GNSS/INS, mounting, delay."),
    bias_h: float = typer.Option(1.5, "--bias-h", help="GNSS position bias, horizontal, m."),
    bias_v: float = typer.Option(2.0, "--bias-v", help="GNSS position bias, vertical, m."),
    random_walk: float = typer.Option(0.02, "--random-walk", help="Position random walk, m/sqrt(s)."),
    white_pos: float = typer.Option(0.2, "--white-pos", help="Position white noise, m."),
    white_att: float = typer.Option(0.05, "--white-att", help="Attitude white noise, deg."),
    vibration: float = typer.Option(0.2, "--vibration", help="Vibration amplitude (~10 Hz), deg."),
    boresight: str | None = typer.Option(None, "--boresight", help="True boresight bx,by,bz deg."),
    lever_arm: str | None = typer.Option(None, "--lever-arm", help="True lever arm x,y,z m (body)."),
    delay: float = typer.Option(0.02, "--delay", help="Camera-to-INS time delay, s."),
    gcps: int = typer.Option(0, "--gcps", help="Number of ground control points."),
    leaks: float = typer.Option(
        1.0, "--leaks", min=0.0, help="Planted heat leaks per building (Poisson mean; 0: none)."
    ),
    netd: float = typer.Option(0.05, "--netd", help="Temporal noise, K."),
    psf: float = typer.Option(0.6, "--psf", help="Gaussian blur sigma, px."),
    column_noise: float = typer.Option(0.03, "--column-noise", help="Fixed-pattern column noise, K."),
    vignetting: float = typer.Option(-0.2, "--vignetting", help="Offset at the corners, K."),
    supersample: int = typer.Option(3, "--supersample", help="Area sampling: N x N rays per pixel at edges."),
    width: int = typer.Option(640, "--width", help="Image width, px."),
    image_height: int = typer.Option(512, "--image-height", help="Image height, px."),
    hfov: float = typer.Option(45.0, "--hfov", help="Horizontal field of view, deg."),
    rgb: bool = typer.Option(
        False, "--rgb", help="Add an RGB camera on the mount (rgb/*.png, the manifest's rgb_camera)."
    ),
    rgb_width: int = typer.Option(1280, "--rgb-width", help="RGB image width, px."),
    rgb_height: int = typer.Option(1024, "--rgb-height", help="RGB image height, px."),
    occluders: bool = typer.Option(
        False, "--occluders", help="Render street trees and parked cars the model lacks (occluders)."
    ),
) -> None:
    """Render a synthetic TIR sequence package of a city model, with a ground-truth file."""
    console = Console()
    if platform not in ("drive", "flight", "terrestrial"):
        raise typer.BadParameter(f"--platform must be drive, flight or terrestrial, got {platform!r}")
    errors = ErrorOptions(
        enabled=not no_errors,
        position_bias_h_m=bias_h,
        position_bias_v_m=bias_v,
        position_random_walk_m=random_walk,
        position_white_m=white_pos,
        attitude_white_deg=white_att,
        vibration_deg=vibration,
        boresight_deg=_triple(boresight, "--boresight"),
        lever_arm_m=_triple(lever_arm, "--lever-arm"),
        time_delay_s=delay,
    )
    drive, flight = DriveOptions(distance_m=distance), FlightOptions(pattern=pattern)  # type: ignore[arg-type]
    terrestrial = TerrestrialOptions(distance_m=distance if distance != 11.0 else 10.0)
    if speed is not None:
        drive, flight = replace(drive, speed_mps=speed), replace(flight, speed_mps=speed)
        terrestrial = replace(terrestrial, speed_mps=speed)
    if height is not None:
        drive, flight = replace(drive, height_m=height), replace(flight, height_m=height)
        terrestrial = replace(terrestrial, height_m=height)
    try:
        if procedural > 0:
            blds, model_path, proc = procedural_block(procedural, seed), None, (procedural, seed)
        else:
            from db.citygml import CityGMLError
            from db.citygml.reader import read_model

            model_path = model or BUNDLED_MODEL
            proc = None
            try:
                _, blds = read_model(model_path)
            except (CityGMLError, OSError) as exc:
                console.print(f"[red]error:[/red] {model_path}: {exc}")
                raise typer.Exit(code=1) from None
        options = SynthOptions(
            platform=platform,  # type: ignore[arg-type]
            n_frames=frames,
            seed=seed,
            buildings=_cluster(buildings),
            frame_interval_s=interval,
            camera=default_camera(width, image_height, hfov),
            drive=drive,
            flight=flight,
            terrestrial=terrestrial,
            thermal=ThermalOptions(leaks_per_building=leaks),
            errors=errors,
            sensor=SensorOptions(
                psf_sigma_px=psf,
                netd_k=netd,
                column_noise_k=column_noise,
                vignetting_k=vignetting,
                supersample=supersample,
            ),
            n_gcps=gcps,
            rgb=RgbOptions(width=rgb_width, height=rgb_height) if rgb else None,
            occluders=OccluderOptions() if occluders else None,
            model_path=str(Path(model_path).resolve()) if model_path else None,
            procedural=proc,
        )
        result = synthesize(blds, options)
        with Progress(
            TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), console=console
        ) as progress:
            task = progress.add_task("frames", total=frames)
            wrapped = _Progress(result.frames, progress, task)
            write_synthetic_package(result, out, truth, frames=wrapped)
    except (SynthError, PackageError, OSError) as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=1) from None
    tp = truth if truth is not None else out.with_name(out.name + ".truth.json")
    t = result.truth
    console.print(
        f"[green]wrote[/green] {out} ({frames} frames{', with an RGB camera' if rgb else ''}, {platform}), "
        f"truth {tp}\n"
        f"  scene: {len(t.buildings)} buildings, cluster {len(t.cluster)}, {len(t.anomalies)} anomalies, "
        f"ground z {t.ground_z:.2f} m, crs {t.crs}\n"
        f"  true boresight {list(map(float, t.true_mounting.boresight_deg))} deg, "
        f"lever arm {list(map(float, t.true_mounting.lever_arm_m))} m, delay {t.time_delay_s} s"
    )


def register(root: typer.Typer) -> None:
    """Add `citytherm synth` to the root app."""
    root.command("synth")(synth)
