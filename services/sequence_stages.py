"""The sequence stages of a job before its building units (`DESIGN.md`: ingest, calibrate,
plan, units, finish): calibrate and, for close-range sequences, orient.

In: the buildings near the cameras, the manifest, its prior poses, the frames.
Out: calibrate: a `SequenceCalibration` (boresight, GNSS offset, lever arm, time delay;
`calibrate.py`), the calibrated priors and accuracy the building units start from, and the
`orientation.json` `mounting` / `report.json` `calibration` documents; orient: a
`SequenceOrientation` (`orient_sequence.py`: every frame's pose refined in blocks of feature
tracks and a bundle adjustment with the model), whose poses, covariances and tracks the units
refine from. The orientation modules are imported where the stages run: the runner stays
importable without them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Accuracy, FrameSource, Mounting, SequenceManifest
from workers.pipeline.geometry.pose import Pose

if TYPE_CHECKING:
    from workers.pipeline.geometry.raycast import RayCaster
    from workers.pipeline.orientation.calibration import SequenceCalibration
    from workers.pipeline.orientation.sequence import SequenceOrientation

__all__ = ["calibrate_priors", "calibration_documents", "orient_priors", "orients"]


def calibrate_priors(
    buildings: Sequence[Building],
    manifest: SequenceManifest,
    priors: Sequence[Pose],
    frame_source: FrameSource,
    caster: RayCaster | None = None,
) -> tuple[SequenceCalibration, list[Pose], Accuracy | None]:
    """The calibrate stage: `calibrate_sequence` over every frame of the sequence against a ray
    caster over `buildings` (those near the cameras).

    Args:
        buildings: the buildings within reach of the cameras (world = model CRS).
        manifest: the sequence (camera, frame indices and times in seconds, accuracy).
        priors: manifest-only prior camera pose per frame, in manifest order.
        frame_source: the package's frames (`load(index)`, physical values).
        caster: a ray caster over `buildings` (built here when None; the orient stage shares it).

    Returns:
        (the calibration, the priors the units start from (`apply_calibration`: unchanged unless
        accepted), their a-priori accuracy (`calibrated_accuracy`; the manifest's unless
        accepted)). A calibration that raises is returned as rejected, its `reason` naming the
        error: one sequence the method cannot handle must not sink the job.
    """
    from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
    from workers.pipeline.orientation.calibration import (
        SequenceCalibration,
        apply_calibration,
        calibrate_sequence,
        calibrated_accuracy,
    )

    frames = [f.index for f in manifest.frames]
    times = [float(f.time) for f in manifest.frames]
    if not buildings:
        cal = SequenceCalibration(theta=np.zeros(10), reason="no buildings near the cameras")
    else:
        try:
            caster = caster if caster is not None else RayCaster(build_scene_mesh(buildings))
            cal = calibrate_sequence(
                manifest.camera,
                caster,
                frames,
                frame_source,
                dict(zip(frames, priors, strict=True)),
                dict(zip(frames, times, strict=True)),
                manifest.accuracy,
            )
        except Exception as exc:  # reported in report.json: the job goes on
            cal = SequenceCalibration(theta=np.zeros(10), reason=f"failed: {type(exc).__name__}: {exc}")
    calibrated = apply_calibration(list(priors), times, cal)
    return cal, calibrated, calibrated_accuracy(cal, prior=manifest.accuracy)


def calibration_documents(
    calibration: SequenceCalibration | None, mounting: Mounting, seconds: float | None = None
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """orientation.json `mounting` (None: the manifest's `mounting`, no delay) and report.json
    `calibration` (`{"run": false}` when the stage did not run; `seconds` its wall time)."""
    if calibration is None:
        return None, {"run": False}
    from workers.pipeline.orientation.mounting import calibration_report, mounting_document

    return mounting_document(mounting, calibration), calibration_report(calibration, mounting, seconds)


def orients(platform: str) -> bool:
    """True when sequences of `platform` are oriented in blocks before the units (close range:
    `orient_sequence.SEQUENCE_PLATFORMS`)."""
    from workers.pipeline.orientation.sequence import SEQUENCE_PLATFORMS

    return platform in SEQUENCE_PLATFORMS


def orient_priors(
    buildings: Sequence[Building],
    manifest: SequenceManifest,
    priors: Sequence[Pose],
    frame_source: FrameSource,
    accuracy: Accuracy | None,
    progress: Callable[[int, int], None] | None = None,
    caster: RayCaster | None = None,
) -> tuple[SequenceOrientation | None, dict[str, Any]]:
    """The orient stage: `orient_sequence` over every frame of the sequence, from the
    (calibrated) `priors` with their `accuracy`, against a ray caster over `buildings` (`caster`,
    built here when None).

    Returns (the orientation, or None when it could not run, and the report.json
    `sequence_orientation` block). An orientation that raises is reported, not fatal: the units
    then refine from the priors.
    """
    from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
    from workers.pipeline.orientation.sequence import orient_sequence

    if not buildings:
        return None, {"run": False, "reason": "no buildings near the cameras"}
    frames = [f.index for f in manifest.frames]
    times = {f.index: float(f.time) for f in manifest.frames}
    try:
        caster = caster if caster is not None else RayCaster(build_scene_mesh(buildings))
        prior = dict(zip(frames, priors, strict=True))
        so = orient_sequence(manifest.camera, caster, frames, frame_source, prior, times, accuracy,
                             progress=progress)
    except Exception as exc:  # reported in report.json: the job goes on
        return None, {"run": False, "reason": f"failed: {type(exc).__name__}: {exc}"}
    return so, {"run": True, **so.to_dict()}
