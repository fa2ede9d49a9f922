"""Direct georeferencing: GNSS/INS solution + mounting -> camera poses in the world frame.

In: a `SequenceManifest` (frame positions in the manifest's `crs`, attitudes `[roll, pitch,
heading]` in degrees, mounting, optional high-rate IMU samples), the city model's CRS.
Out: `Pose` objects (`R_world_from_cam`, `center`) in the world frame = the model's projected
CRS (x east, y north, z up, metres).

Conventions (exactly `sequence-format.md`):

- `R_ned_from_body = Rz(heading) · Ry(pitch) · Rx(roll)` (NED: x north, y east, z down; body:
  x forward, y right, z down), right-hand rotations.
- `R_world_from_ned = [[0,1,0],[1,0,0],[0,0,-1]]`, heading from grid north. A `"true"` heading
  is first reduced by the meridian convergence γ of the world CRS at the platform:
  `heading_grid = heading_true − γ` (pyproj's `meridian_convergence`, positive east of the
  central meridian in UTM, where true north points west of grid north).
- `R_body_from_cam = Rz(bz) · Ry(by) · Rx(bx) · M` (exact, never linearised).
- `R_world_from_cam = R_world_from_ned · R_ned_from_body · R_body_from_cam`,
  `C = P + R_world_from_ned · R_ned_from_body · L`.

Time: the true pose of a frame stamped `t` is the INS solution at `t − δ` (camera-to-INS
delay δ). `Trajectory` interpolates positions linearly and attitudes by SLERP (never angles).
Outside the sampled time range `Trajectory.at` raises `GeorefError` unless an extrapolation
margin is allowed: then the end segment's velocity and angular rate are continued.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pyproj
from scipy.spatial.transform import Rotation, Slerp

from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_crs, resolve_crs, same_horizontal
from workers.pipeline.geometry.manifest import ImuSamples, Mounting, SequenceManifest
from workers.pipeline.geometry.pose import Pose

__all__ = [
    "R_WORLD_FROM_NED",
    "GeorefError",
    "Rx",
    "Ry",
    "Rz",
    "Trajectory",
    "attitude_from_ned_from_body",
    "body_from_cam",
    "camera_pose",
    "camera_pose_arrays",
    "camera_poses",
    "ins_from_camera",
    "meridian_convergence_deg",
    "model_positions",
    "ned_from_body",
    "prior_poses",
    "transform_positions",
    "world_trajectory",
]

#: `(3, 3)` NED (x north, y east, z down) -> world (x east, y north, z up).
R_WORLD_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

GEOGRAPHIC_3D = "EPSG:4979"
MODEL = "model"


class GeorefError(ValueError):
    """Georeferencing cannot be done (time outside the trajectory, unknown or mismatched CRS)."""


# -- elementary rotations ------------------------------------------------------------------------
def _elementary(a: float | np.ndarray, i: int, j: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((*a.shape, 3, 3))
    k = 3 - i - j
    R[..., k, k] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def Rx(a: float | np.ndarray) -> np.ndarray:
    """Right-hand rotation about x by `a` radians: `[[1,0,0],[0,c,-s],[0,s,c]]`; `(..., 3, 3)`."""
    return _elementary(a, 1, 2)


def Ry(a: float | np.ndarray) -> np.ndarray:
    """Right-hand rotation about y by `a` radians: `[[c,0,s],[0,1,0],[-s,0,c]]`; `(..., 3, 3)`."""
    return _elementary(a, 2, 0)


def Rz(a: float | np.ndarray) -> np.ndarray:
    """Right-hand rotation about z by `a` radians: `[[c,-s,0],[s,c,0],[0,0,1]]`; `(..., 3, 3)`.

    >>> np.round(Rz(np.pi / 2) @ [1.0, 0.0, 0.0], 12).tolist()
    [0.0, 1.0, 0.0]
    """
    return _elementary(a, 0, 1)


# -- attitude ------------------------------------------------------------------------------------
def ned_from_body(attitude_deg: np.ndarray | Sequence[float]) -> np.ndarray:
    """`[roll, pitch, heading]` degrees `(3,)` or `(N, 3)` -> `R_ned_from_body` `(3, 3)` / `(N, 3, 3)`.

    `Rz(heading) · Ry(pitch) · Rx(roll)`.

    >>> np.round(ned_from_body([0, 0, 90]) @ [1.0, 0, 0], 12).tolist()  # forward = east
    [0.0, 1.0, 0.0]
    """
    att = np.radians(np.asarray(attitude_deg, dtype=np.float64))
    return Rz(att[..., 2]) @ Ry(att[..., 1]) @ Rx(att[..., 0])


def attitude_from_ned_from_body(R: np.ndarray) -> np.ndarray:
    """Inverse of `ned_from_body`: `(3, 3)` / `(N, 3, 3)` -> `[roll, pitch, heading]` degrees,
    heading in [0, 360), pitch in [-90, 90], roll in (-180, 180]."""
    R = np.asarray(R, dtype=np.float64)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    heading = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    out = np.degrees(np.stack([roll, pitch, heading], axis=-1))
    out[..., 2] = np.mod(out[..., 2], 360.0)
    out[..., 2] = np.where(out[..., 2] >= 360.0, 0.0, out[..., 2])
    return out


def body_from_cam(mounting: Mounting) -> np.ndarray:
    """`R_body_from_cam` `(3, 3)` = `Rz(bz) · Ry(by) · Rx(bx) · M` (boresight about body axes
    after the nominal mounting `M` = `camera_to_body`)."""
    bx, by, bz = np.radians(np.asarray(mounting.boresight_deg, dtype=np.float64).reshape(3))
    M = np.asarray(mounting.camera_to_body, dtype=np.float64).reshape(3, 3)
    return Rz(bz) @ Ry(by) @ Rx(bx) @ M


# -- poses ---------------------------------------------------------------------------------------
def _poses_from_rotations(
    positions: np.ndarray, R_ned_from_body: np.ndarray, mounting: Mounting, convergence_deg: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World positions `(N, 3)`, `R_nb` `(N, 3, 3)`, convergence `(N,)` -> (`R_wc` `(N,3,3)`, `C` `(N,3)`)."""
    R_grid = Rz(-np.radians(convergence_deg)) @ R_ned_from_body  # heading reduced by γ
    R_world_from_body = R_WORLD_FROM_NED @ R_grid
    R_wc = R_world_from_body @ body_from_cam(mounting)
    L = np.asarray(mounting.lever_arm_m, dtype=np.float64).reshape(3)
    C = positions + R_world_from_body @ L
    return R_wc, C


def camera_pose_arrays(
    positions_world: np.ndarray,
    attitudes_deg: np.ndarray,
    mounting: Mounting,
    convergence_deg: np.ndarray | float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Array form of `camera_poses`: -> (`R_world_from_cam` `(N, 3, 3)`, centres `(N, 3)` world)."""
    P = np.asarray(positions_world, dtype=np.float64).reshape(-1, 3)
    att = np.asarray(attitudes_deg, dtype=np.float64).reshape(-1, 3)
    gamma = np.broadcast_to(np.asarray(convergence_deg, dtype=np.float64), (len(P),))
    return _poses_from_rotations(P, ned_from_body(att), mounting, gamma)


def camera_poses(
    positions_world: np.ndarray,
    attitudes_deg: np.ndarray,
    mounting: Mounting,
    convergence_deg: np.ndarray | float = 0.0,
) -> list[Pose]:
    """Vectorised `camera_pose`: positions `(N, 3)` world metres, attitudes `(N, 3)` degrees,
    convergence `(N,)` or scalar degrees (0 for grid headings) -> N poses."""
    R_wc, C = camera_pose_arrays(positions_world, attitudes_deg, mounting, convergence_deg)
    return [Pose(R_wc[i], C[i]) for i in range(len(C))]


def ins_from_camera(
    pose: Pose, mounting: Mounting, convergence_deg: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `camera_pose`: the GNSS/INS solution that yields `pose` with `mounting`.

    Returns (IMU reference point `(3,)` in world metres, `[roll, pitch, heading]` degrees, the
    heading true when `convergence_deg` is given, grid otherwise). Used to write synthetic
    manifests from designed camera poses.
    """
    R_world_from_body = pose.R_world_from_cam @ body_from_cam(mounting).T
    R_grid = R_WORLD_FROM_NED.T @ R_world_from_body
    R_ned_from_body = Rz(np.radians(convergence_deg)) @ R_grid
    L = np.asarray(mounting.lever_arm_m, dtype=np.float64).reshape(3)
    return pose.center - R_world_from_body @ L, attitude_from_ned_from_body(R_ned_from_body)


def camera_pose(
    position_world: np.ndarray | Sequence[float],
    attitude_deg: np.ndarray | Sequence[float],
    mounting: Mounting,
    convergence_deg: float = 0.0,
) -> Pose:
    """One camera pose from the IMU reference point `position_world` `(3,)` (world metres),
    `attitude_deg` `[roll, pitch, heading]` and the mounting. `convergence_deg` is the meridian
    convergence to subtract from a true heading (0 for grid headings)."""
    return camera_poses(
        np.reshape(position_world, (1, 3)), np.reshape(attitude_deg, (1, 3)), mounting, convergence_deg
    )[0]


# -- CRS -----------------------------------------------------------------------------------------
def meridian_convergence_deg(
    crs: str | pyproj.CRS, x: np.ndarray | float, y: np.ndarray | float
) -> np.ndarray:
    """Meridian convergence γ (degrees) of projected `crs` at world points `x, y` (metres).

    γ is the angle from true north to grid north: a true heading becomes a grid heading as
    `heading − γ` (UTM, east of the central meridian in the north: γ > 0). Shape of `x`.
    """
    h = horizontal_crs(crs)
    if not h.is_projected:
        raise GeorefError(f"meridian convergence needs a projected CRS, got {h.name!r}")
    geo = h.geodetic_crs
    lon, lat = pyproj.Transformer.from_crs(h, geo, always_xy=True).transform(
        np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    )
    factors = pyproj.Proj(h).get_factors(np.asarray(lon), np.asarray(lat))
    return np.asarray(factors.meridian_convergence, dtype=np.float64)


def transform_positions(
    positions: np.ndarray,
    source_crs: str,
    model_crs: str | pyproj.CRS | None,
    vertical_offset_m: float = 0.0,
) -> np.ndarray:
    """Positions `(N, 3)` in `source_crs` -> world `(N, 3)` in the model CRS, plus the vertical offset.

    `source_crs`: `"model"` (already in model coordinates: passthrough), `"EPSG:4979"` or
    another geographic CRS (`[lat, lon, ellipsoidal height]`: horizontal transformation, height
    kept), or any resolvable
    projected CRS (passthrough when its horizontal CRS equals the model's, otherwise transformed
    horizontally; heights are kept in both cases). `model_crs=None` means "the manifest's CRS
    is the world" (only valid for projected or `"model"` sources).
    """
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3).copy()
    src = source_crs.strip()
    if src.lower() != MODEL:
        try:
            src_crs = resolve_crs(src)
        except UnknownCRSError as exc:
            raise GeorefError(f"crs: {exc}") from exc
        src_h = horizontal_crs(src_crs)
        if model_crs is None:
            if not src_h.is_projected:
                raise GeorefError(f"crs {src!r} is not projected: a model CRS is needed to place it")
        else:
            dst_h = horizontal_crs(model_crs)
            if src_h.is_geographic:
                # positions are [lat, lon, h] (EPSG:4979); world is always (east, north)
                tr = pyproj.Transformer.from_crs(src_h, dst_h, always_xy=True)
                P[:, 0], P[:, 1] = tr.transform(P[:, 1].copy(), P[:, 0].copy())
            elif not same_horizontal(src_h, dst_h):
                tr = pyproj.Transformer.from_crs(src_h, dst_h, always_xy=True)
                P[:, 0], P[:, 1] = tr.transform(P[:, 0], P[:, 1])
            if not np.all(np.isfinite(P)):
                raise GeorefError(f"positions in {src!r} could not be transformed to {dst_h.name!r}")
    P[:, 2] += float(vertical_offset_m)
    return P


def model_positions(manifest: SequenceManifest, model_crs: str | pyproj.CRS | None) -> np.ndarray:
    """Frame positions of the manifest as world coordinates `(N, 3)` in the model CRS."""
    P = np.array([f.position for f in manifest.frames], dtype=np.float64).reshape(-1, 3)
    return transform_positions(P, manifest.crs, model_crs, manifest.vertical_offset_m)


def _world_crs(manifest: SequenceManifest, model_crs: str | pyproj.CRS | None) -> str | pyproj.CRS | None:
    if model_crs is not None:
        return model_crs
    return None if manifest.crs.strip().lower() == MODEL else manifest.crs


def _convergence(manifest: SequenceManifest, model_crs: str | pyproj.CRS | None, P: np.ndarray) -> np.ndarray:
    if manifest.heading_reference == "grid":
        return np.zeros(len(P))
    if manifest.heading_reference != "true":
        raise GeorefError(
            f"attitude.heading_reference: {manifest.heading_reference!r} is not 'grid' or 'true'"
        )
    world = _world_crs(manifest, model_crs)
    if world is None:
        raise GeorefError("attitude.heading_reference 'true' needs a known (projected) model CRS")
    return meridian_convergence_deg(world, P[:, 0], P[:, 1])


# -- time interpolation --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Trajectory:
    """GNSS/INS solution over time: `times` `(N,)` strictly increasing seconds, `positions`
    `(N, 3)` (any frame, usually world), `R_ned_from_body` `(N, 3, 3)`.

    Positions are interpolated linearly, rotations by SLERP (so 359.9° -> 0.1° passes north).
    """

    times: np.ndarray
    positions: np.ndarray
    R_ned_from_body: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        P = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        R = np.asarray(self.R_ned_from_body, dtype=np.float64).reshape(-1, 3, 3)
        if not (len(t) == len(P) == len(R)) or len(t) == 0:
            raise GeorefError(f"trajectory: {len(t)} times, {len(P)} positions, {len(R)} rotations")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise GeorefError("trajectory: times must be finite and strictly increasing")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "positions", P)
        object.__setattr__(self, "R_ned_from_body", R)

    @classmethod
    def from_samples(cls, times: np.ndarray, positions: np.ndarray, attitudes_deg: np.ndarray) -> Trajectory:
        """From times `(N,)`, positions `(N, 3)`, attitudes `[roll, pitch, heading]` `(N, 3)` degrees."""
        return cls(np.asarray(times), np.asarray(positions), ned_from_body(np.asarray(attitudes_deg)))

    @classmethod
    def from_frames(cls, manifest: SequenceManifest) -> Trajectory:
        """The frames' own solution (positions in the manifest's `crs`)."""
        fr = manifest.frames
        return cls.from_samples(
            np.array([f.time for f in fr]),
            np.array([f.position for f in fr]).reshape(-1, 3),
            np.array([f.attitude_deg for f in fr]).reshape(-1, 3),
        )

    @classmethod
    def from_imu(cls, imu: ImuSamples) -> Trajectory:
        """The high-rate IMU solution (positions in the manifest's `crs`)."""
        return cls.from_samples(imu.time, imu.position, imu.attitude_deg)

    @cached_property
    def _rotations(self) -> Rotation:
        return Rotation.from_matrix(self.R_ned_from_body)

    @cached_property
    def _slerp(self) -> Slerp:
        return Slerp(self.times, self._rotations)

    def with_positions(self, positions: np.ndarray) -> Trajectory:
        """The same trajectory with positions replaced (e.g. transformed into the world CRS)."""
        return Trajectory(self.times, positions, self.R_ned_from_body)

    def at(self, times: np.ndarray, max_extrapolation_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Interpolate at `times` `(M,)` -> (positions `(M, 3)`, `R_ned_from_body` `(M, 3, 3)`).

        Times more than `max_extrapolation_s` outside `[times[0], times[-1]]` raise `GeorefError`;
        within the margin the first/last segment's velocity and angular rate are continued
        (a single-sample trajectory stays constant).
        """
        q = np.atleast_1d(np.asarray(times, dtype=np.float64))
        t0, t1 = self.times[0], self.times[-1]
        eps = 1e-9 * max(1.0, abs(t0), abs(t1))
        bad = (q < t0 - max_extrapolation_s - eps) | (q > t1 + max_extrapolation_s + eps) | ~np.isfinite(q)
        if np.any(bad):
            raise GeorefError(
                f"time {q[bad][0]!r} outside the trajectory [{t0!r}, {t1!r}] "
                f"(extrapolation allowed: {max_extrapolation_s} s)"
            )
        n = len(self.times)
        if n == 1:
            return np.repeat(self.positions, len(q), axis=0), np.repeat(self.R_ned_from_body, len(q), axis=0)
        # segment index and fraction (fraction < 0 or > 1 extrapolates the end segment)
        i = np.clip(np.searchsorted(self.times, q, side="right") - 1, 0, n - 2)
        ta, tb = self.times[i], self.times[i + 1]
        f = (q - ta) / (tb - ta)
        P = (1.0 - f)[:, None] * self.positions[i] + f[:, None] * self.positions[i + 1]
        rot = self._rotations
        inside = (f >= 0.0) & (f <= 1.0)
        R = np.empty((len(q), 3, 3))
        if np.any(inside):
            R[inside] = self._slerp(np.clip(q[inside], t0, t1)).as_matrix()
        if np.any(~inside):
            ra, rb = rot[i[~inside]], rot[i[~inside] + 1]
            delta = (ra.inv() * rb).as_rotvec()  # body-frame increment over the segment
            R[~inside] = (ra * Rotation.from_rotvec(delta * f[~inside, None])).as_matrix()
        # exact samples where a query hits a sample time
        R[f == 0.0] = self.R_ned_from_body[i[f == 0.0]]
        R[f == 1.0] = self.R_ned_from_body[i[f == 1.0] + 1]
        return P, R


def world_trajectory(manifest: SequenceManifest, model_crs: str | pyproj.CRS | None) -> Trajectory:
    """IMU trajectory (or the frames' when there is no IMU) with positions in world coordinates
    (model CRS, vertical offset applied). Build it once when querying many time delays."""
    traj = Trajectory.from_imu(manifest.imu) if manifest.imu is not None else Trajectory.from_frames(manifest)
    return traj.with_positions(
        transform_positions(traj.positions, manifest.crs, model_crs, manifest.vertical_offset_m)
    )


def prior_poses(
    manifest: SequenceManifest,
    model_crs: str | pyproj.CRS | None,
    time_delay_s: float = 0.0,
    mounting: Mounting | None = None,
) -> list[Pose]:
    """Camera poses of all frames in the world frame (model CRS).

    With `time_delay_s == 0` the frames' own positions and attitudes are used (the spec's prior
    poses); otherwise the INS solution at `time − δ`, interpolated from `imu.csv` when present,
    else from the frames (extrapolating the end segments by at most |δ|). `mounting` overrides
    the manifest's (e.g. a calibrated boresight and lever arm).
    """
    mnt = mounting if mounting is not None else manifest.mounting
    if time_delay_s == 0.0:
        P = model_positions(manifest, model_crs)
        R_nb = ned_from_body(np.array([f.attitude_deg for f in manifest.frames]).reshape(-1, 3))
    else:
        traj = world_trajectory(manifest, model_crs)
        t = np.array([f.time for f in manifest.frames], dtype=np.float64) - float(time_delay_s)
        P, R_nb = traj.at(t, max_extrapolation_s=abs(float(time_delay_s)))
    gamma = _convergence(manifest, model_crs, P)
    R_wc, C = _poses_from_rotations(P, R_nb, mnt, gamma)
    return [Pose(R_wc[i], C[i]) for i in range(len(P))]
