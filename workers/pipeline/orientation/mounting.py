"""A sequence calibration (`calibration.SequenceCalibration`) in the manifest's mounting terms.

In: the manifest's `Mounting` (nominal `M`, boresight `b0 = [bx, by, bz]` degrees about body
axes, lever arm `L0` body metres) and an accepted calibration θ = (ω camera rad, b world m,
l camera m, τ s).
Out: the full estimated mounting (`docs/results-format.md`, orientation.json `mounting`: the
estimated values, not corrections), and JSON-ready blocks for `orientation.json` and
`report.json`.

Conventions (`docs/sequence-format.md`): `R_bc = Rb(boresight) · M`, `Rb = Rz(bz)·Ry(by)·Rx(bx)`,
`R_wc = R_wb · R_bc`, `C = P + R_wb · L`. The calibration corrects a prior pose as
`R_wc' = R_wc · exp([ω]×)` and `C' = C + b + R_wc · l` (`calibration_model.design`, with `R_wc`
the *prior* rotation), hence:

- `R_bc' = Rb0 · M · exp([ω]×)`, so `Rb' = Rb0 · M · exp([ω]×) · Mᵀ`, decomposed z-y-x like an
  attitude (`geometry.georef.attitude_from_ned_from_body`: `Rz(heading)·Ry(pitch)·Rx(roll)` is
  the same product as `Rz(bz)·Ry(by)·Rx(bx)`), each angle wrapped to (−180°, 180°];
- `L' = L0 + R_bc0 · l` (`R_bc0 = Rb0 · M`, the prior's camera-to-body rotation, exactly the
  rotation `calibration_model.design` applies to `l`; using the corrected `R_bc'` instead would
  differ by `ω × l`, second order);
- `time_delay_s = τ`; the GNSS offset `b` (world) is no mounting term and is reported apart.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.pipeline.geometry.georef import attitude_from_ned_from_body, body_from_cam
from workers.pipeline.geometry.manifest import Mounting
from workers.pipeline.geometry.pose_increments import so3_exp
from workers.pipeline.orientation.calibration import SequenceCalibration

__all__ = [
    "calibrated_mounting",
    "calibration_report",
    "mounting_document",
    "wrap_deg",
]


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Angles (degrees, any shape) wrapped to (−180, 180]."""
    w = np.mod(np.asarray(a, dtype=np.float64) + 180.0, 360.0) - 180.0
    return np.where(w <= -180.0, w + 360.0, w)


def calibrated_mounting(mounting: Mounting, calibration: SequenceCalibration) -> Mounting:
    """The full mounting a calibration estimates (module docstring), whatever its acceptance.

    Args:
        mounting: the manifest's mounting (`camera_to_body` `(3, 3)`, `boresight_deg` `(3,)`,
            `lever_arm_m` `(3,)` body axes, metres).
        calibration: `theta` `(10,)` = ω (camera frame, rad), b (world, m), l (camera frame, m), τ (s).

    Returns:
        `Mounting` with the same `M`, `boresight_deg` `(3,)` = `[bx, by, bz]` degrees in
        (−180, 180] and `lever_arm_m` `(3,)` body metres.
    """
    M = np.asarray(mounting.camera_to_body, dtype=np.float64).reshape(3, 3)
    R_bc0 = body_from_cam(mounting)
    Rb_new = R_bc0 @ so3_exp(calibration.boresight_rad) @ M.T
    boresight = wrap_deg(attitude_from_ned_from_body(Rb_new))
    lever = np.asarray(mounting.lever_arm_m, dtype=np.float64).reshape(3) + R_bc0 @ calibration.lever_arm_m
    return Mounting(camera_to_body=M.copy(), boresight_deg=boresight, lever_arm_m=lever)


def mounting_document(mounting: Mounting, calibration: SequenceCalibration | None) -> dict[str, Any]:
    """orientation.json `mounting`: the estimated boresight (degrees), lever arm (body metres)
    and time delay (seconds) when `calibration` was accepted; else the manifest's values and 0."""
    if calibration is not None and calibration.accepted:
        m = calibrated_mounting(mounting, calibration)
        delay = calibration.time_delay_s
    else:
        m, delay = mounting, 0.0
    return {
        "boresight_deg": np.asarray(m.boresight_deg, dtype=float).reshape(3).tolist(),
        "lever_arm_m": np.asarray(m.lever_arm_m, dtype=float).reshape(3).tolist(),
        "time_delay_s": float(delay),
    }


def calibration_report(
    calibration: SequenceCalibration | None, mounting: Mounting | None = None, seconds: float | None = None
) -> dict[str, Any]:
    """report.json `calibration`: `{"run": false}` when no calibration ran; else `run: true`,
    `SequenceCalibration.to_dict()`, the GNSS offset `gnss_offset_m` `(3,)` (world east, north,
    up, metres; not a mounting term), the estimated `mounting` (as in orientation.json, when
    `mounting` is given) and the wall time `seconds`."""
    if calibration is None:
        return {"run": False}
    doc: dict[str, Any] = {"run": True, **calibration.to_dict()}
    doc["gnss_offset_m"] = np.asarray(calibration.offset_m, dtype=float).round(4).tolist()
    if mounting is not None:
        doc["mounting"] = mounting_document(mounting, calibration)
    if seconds is not None:
        doc["seconds"] = round(float(seconds), 2)
    return doc
