"""Quality measures of model-to-image coregistration on synthetic ground truth (Avbelj et al. 2012).

In: reprojection errors before/after refinement, extracted image points, matches, and the true
image positions of model corners (projected with the true pose). Out: shares in 0..1.

- efficiency: share of frames whose refined projection fits the truth better than the prior;
- completeness / correctness of feature extraction: share of true corner positions with an
  extracted point within a tolerance / share of extracted points near a true corner position;
- completeness / correctness of matching: share of model corners correctly matched / share of
  matches whose image point lies within the tolerance of the matched corner's true position;
- tie points (`tracks`): the distance of every later observation of a track to its true
  correspondence.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.tracks import Tracks


def edge_points(building: Building, spacing_m: float = 0.5) -> np.ndarray:
    """Points `(N, 3)` (model CRS) every `spacing_m` metres along all polygon edges of
    `building`, parts included (vertices included)."""
    out = []
    for poly in building.iter_polygons():
        for ring in poly.rings:
            for a, b in itertools.pairwise(ring.coords):
                k = max(int(np.ceil(np.linalg.norm(b - a) / spacing_m)), 1)
                out.append(a + np.linspace(0, 1, k, endpoint=False)[:, None] * (b - a))
    return np.concatenate(out)


def reprojection_rms(
    camera: Camera, points: np.ndarray, pose: Pose, truth: Pose, min_points: int = 1
) -> float:
    """RMS pixel distance between `points (N, 3)` projected with `pose` and with `truth`, over the
    points the true pose sees in front and inside the frame; NaN when fewer than `min_points`.
    A point behind the camera of `pose` counts as 1000 px off."""
    b, zb = truth.project(camera, points)
    ok = (zb > 1.0) & camera.in_image(b)
    if ok.sum() < max(min_points, 1):
        return float("nan")
    a, za = pose.project(camera, points[ok])
    d = np.sum((a - b[ok]) ** 2, axis=1)
    d = np.where((za > 0.1) & np.isfinite(d), d, 1e6)
    return float(np.sqrt(np.mean(d)))


def efficiency(error_prior: Sequence[float], error_refined: Sequence[float]) -> float:
    """Share of frames with `error_refined < error_prior` (errors in px; NaN pairs ignored).

    >>> efficiency([5.0, 5.0, 1.0], [1.0, 6.0, 0.5])
    0.6666666666666666
    """
    a = np.asarray(error_prior, dtype=np.float64)
    b = np.asarray(error_refined, dtype=np.float64)
    ok = np.isfinite(a) & ~np.isnan(b)
    if not ok.any():
        return float("nan")
    return float(np.mean(b[ok] < a[ok]))


def point_quality(
    found_uv: np.ndarray, true_uv: np.ndarray, tolerance_px: float = 2.0
) -> tuple[float, float]:
    """(completeness, correctness) of extracted points `(N, 2)` against true corner positions `(M, 2)`."""
    f = np.asarray(found_uv, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(true_uv, dtype=np.float64).reshape(-1, 2)
    if len(t) == 0 or len(f) == 0:
        return (0.0 if len(t) else float("nan")), (0.0 if len(f) else float("nan"))
    d = np.linalg.norm(f[:, None, :] - t[None, :, :], axis=2)
    completeness = float(np.mean(d.min(axis=0) <= tolerance_px))
    correctness = float(np.mean(d.min(axis=1) <= tolerance_px))
    return completeness, correctness


def match_quality(
    matched_corner: np.ndarray, matched_uv: np.ndarray, true_uv: np.ndarray, tolerance_px: float = 2.0
) -> tuple[float, float]:
    """(completeness, correctness) of matches.

    Args:
        matched_corner: `(K,)` index into `true_uv` of the model corner of each match.
        matched_uv: `(K, 2)` image point each corner was matched to.
        true_uv: `(M, 2)` true image positions of the visible model corners.
    """
    idx = np.asarray(matched_corner, dtype=int).reshape(-1)
    uv = np.asarray(matched_uv, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(true_uv, dtype=np.float64).reshape(-1, 2)
    if len(idx) == 0:
        return (0.0 if len(t) else float("nan")), float("nan")
    good = np.linalg.norm(uv - t[idx], axis=1) <= tolerance_px
    completeness = float(len(np.unique(idx[good])) / len(t)) if len(t) else float("nan")
    return completeness, float(np.mean(good))


def tie_errors(tracks: Tracks, camera: Camera, truth: Sequence[Pose], caster: RayCaster) -> np.ndarray:
    """Pixel distance `(K,)` of every later observation of each track to its true correspondence:
    the ray of its first observation from the true pose onto the model (`caster`), projected
    with the true pose (`truth[frame]`) of the later frame. Observations whose first ray meets
    nothing are left out."""
    first: dict[int, int] = {}
    out = []
    for k, t in enumerate(tracks.track):
        k0 = first.setdefault(int(t), k)
        if k0 == k:
            continue
        a, b = int(tracks.frame[k0]), int(tracks.frame[k])
        d = camera.bearing(tracks.uv[k0][None]) @ truth[a].R_world_from_cam.T
        hit = caster.cast(truth[a].center[None], d)
        if hit.hit[0]:
            uv, _ = truth[b].project(camera, truth[a].center + hit.t[0] * d)
            out.append(float(np.linalg.norm(uv[0] - tracks.uv[k])))
    return np.asarray(out)
