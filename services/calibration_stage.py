"""The calibrate stage of a job (`DESIGN.md`: ingest, calibrate, plan, units, finish).

In: the buildings near the cameras, the manifest, its manifest-only prior poses, the frames.
Out: a `SequenceCalibration` (boresight, GNSS offset, lever arm, time delay; `calibrate.py`), the
calibrated priors and accuracy the building units start from, and the `orientation.json`
`mounting` / `report.json` `calibration` documents. The orientation modules are imported where
the stage runs: the runner stays importable without them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from workers.pipeline.citymodel import Building
from workers.pipeline.pose import Pose
from workers.pipeline.sequence import Accuracy, FrameSource, Mounting, SequenceManifest

if TYPE_CHECKING:
    from workers.pipeline.calibrate import SequenceCalibration

__all__ = ["calibrate_priors", "calibration_documents"]


def calibrate_priors(
    buildings: Sequence[Building],
    manifest: SequenceManifest,
    priors: Sequence[Pose],
    frame_source: FrameSource,
) -> tuple[SequenceCalibration, list[Pose], Accuracy | None]:
    """The calibrate stage: `calibrate_sequence` over every frame of the sequence against a ray
    caster over `buildings` (those near the cameras).

    Args:
        buildings: the buildings within reach of the cameras (world = model CRS).
        manifest: the sequence (camera, frame indices and times in seconds, accuracy).
        priors: manifest-only prior camera pose per frame, in manifest order.
        frame_source: the package's frames (`load(index)`, physical values).

    Returns:
        (the calibration, the priors the units start from (`apply_calibration`: unchanged unless
        accepted), their a-priori accuracy (`calibrated_accuracy`; the manifest's unless
        accepted)). A calibration that raises is returned as rejected, its `reason` naming the
        error: one sequence the method cannot handle must not sink the job.
    """
    from workers.pipeline.calibrate import (
        SequenceCalibration,
        apply_calibration,
        calibrate_sequence,
        calibrated_accuracy,
    )
    from workers.pipeline.raycast import RayCaster, build_scene_mesh

    frames = [f.index for f in manifest.frames]
    times = [float(f.time) for f in manifest.frames]
    if not buildings:
        cal = SequenceCalibration(theta=np.zeros(10), reason="no buildings near the cameras")
    else:
        try:
            caster = RayCaster(build_scene_mesh(buildings))
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
    from workers.pipeline.calibrate_mounting import calibration_report, mounting_document

    return mounting_document(mounting, calibration), calibration_report(calibration, mounting, seconds)
