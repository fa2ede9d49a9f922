"""What the orientation stages assume a priori about the GNSS/INS poses, in one place.

In: a prior `Pose`, the manifest's `Accuracy` (or None), options. Out: `PriorOptions` (the
per-frame deviation σ and the null shift of the edge-support test, shared by every stage), the
information matrix of a prior pose on the correction `δ = (ω_cam [rad], dC_world [m])`
(`prior_information`), and the per-frame deviation as a covariance or an information matrix
(`frame_noise_covariance`, `frame_noise_information`).

The GNSS/INS errors of consecutive frames are a common part (boresight misalignment, GNSS bias,
slow drift) plus each frame's own white noise and vibration. The per-frame σ of `PriorOptions`
is that own part: the deviation of a frame's correction from its neighbours' (`building`: the
neighbour prediction), from the common correction (`common_correction`), from the block's
common error (`block`, `bundle`) and from the systematic model (`calibration`).

The null shift: a pose's edge support (share of projected wireframe samples with an image edge
within the search's tolerance, `edge_observations.edge_support`) is compared with the support of
the same samples moved this far off their edges along the image normal, which edge clutter and
noise alone give (the block's anchoring, the calibration's acceptance).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from workers.pipeline.geometry.manifest import Accuracy
from workers.pipeline.geometry.pose import Pose

__all__ = [
    "PriorOptions",
    "PriorSigmaOptions",
    "frame_noise_covariance",
    "frame_noise_information",
    "prior_information",
]


@dataclass(frozen=True)
class PriorOptions:
    """The a-priori figures every orientation stage shares (degrees, metres, pixels)."""

    # per-frame deviation of a frame's pose correction from what it shares with the other frames
    # (its neighbours, the common correction, the block's common error, the calibration model):
    # white GNSS noise and vibration, standard deviations of the rotation and of the position
    frame_sigma_deg: float = 0.3
    frame_sigma_m: float = 0.3
    # the null support of a pose's edge support: the samples moved this far off their edges
    # along the image normal (edge clutter and noise alone), pixels
    null_shift_px: float = 6.0


class PriorSigmaOptions(Protocol):
    """The prior's standard deviations of an options class (`building.CoregisterOptions`):
    a-priori σ when the manifest has no `accuracy` (metres, degrees), the factor the manifest's σ
    are multiplied by, and their floors (metres, degrees)."""

    @property
    def default_position_sigma_m(self) -> float: ...

    @property
    def default_attitude_sigma_deg(self) -> float: ...

    @property
    def prior_sigma_scale(self) -> float: ...

    @property
    def position_sigma_floor_m(self) -> float: ...

    @property
    def attitude_sigma_floor_deg(self) -> float: ...


def prior_information(prior: Pose, accuracy: Accuracy | None, options: PriorSigmaOptions) -> np.ndarray:
    """Information matrix `(6, 6)` of the prior on `δ = (ω_cam [rad], dC_world [m])`.

    Position σ east, north, up from `accuracy.position_m`; attitude σ roll, pitch, heading
    taken about the world's horizontal axes (roll, pitch, the larger of the two) and the vertical
    (heading), rotated into the camera frame. Both scaled by `prior_sigma_scale` and floored.
    """
    if accuracy is None:
        sp = np.full(3, options.default_position_sigma_m)
        sa = np.full(3, options.default_attitude_sigma_deg)
    else:
        sp = np.broadcast_to(np.asarray(accuracy.position_m, dtype=np.float64), (3,))
        sa = np.broadcast_to(np.asarray(accuracy.attitude_deg, dtype=np.float64), (3,))
    sp = np.maximum(sp * options.prior_sigma_scale, options.position_sigma_floor_m)
    sa = np.maximum(sa * options.prior_sigma_scale, options.attitude_sigma_floor_deg)
    h = max(sa[0], sa[1])
    cov_w = np.diag(np.radians([h, h, sa[2]]) ** 2)
    R = prior.R_world_from_cam
    info = np.zeros((6, 6))
    info[:3, :3] = np.linalg.inv(R.T @ cov_w @ R)
    info[3:, 3:] = np.diag(1.0 / sp**2)
    return info


def frame_noise_covariance(sigma_deg: float, sigma_m: float) -> np.ndarray:
    """`(6, 6)` diagonal per-frame deviation of the correction from its neighbours'."""
    return np.diag([np.radians(sigma_deg) ** 2] * 3 + [sigma_m**2] * 3)


def frame_noise_information(options: PriorOptions) -> np.ndarray:
    """`(6, 6)` diagonal information of the per-frame deviation `ε_i` (rad⁻², m⁻²), as the joint
    fit and the calibration weight it."""
    return np.diag([np.radians(options.frame_sigma_deg) ** -2] * 3 + [options.frame_sigma_m**-2] * 3)
