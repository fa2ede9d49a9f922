"""Facade coregistration of a placed reconstruction: its points assigned to the model's planes
and the 7 parameters of a similarity fitted to their point-to-plane distances (robust), tied to
the GNSS/INS placement by its a-priori σ.

Assignment: each point's local normal (PCA of its nearest reconstructed neighbours) groups it
with the model planes of that orientation; the plane is the polygon that the ray from the
camera observing the point hits (`RayCaster`), within `plane_max_distance_m` of the point
along the ray and `plane_max_angle_deg` of the local normal (a point whose neighbourhood is not
planar is tested on the ray alone). Fit: `X' = e^σ R(ω) (X − c) + c + τ` about the camera
centres' mean `c`, Gauss–Newton on `n·X' − d` with Huber weights (scale `plane_loss_m`) and the prior
`(ω, τ, σ) ~ N(0, diag(σ_att², σ_pos², σ_scale²))`; points re-assigned each round. One plane
fixes the shift along its normal and the two tilts about axes in it; what planes leave open
(a single facade's in-plane shift and its rotation about the normal) stays at the prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.similarity import Similarity, similarity_about


@dataclass(frozen=True, eq=False)
class PlaneAssignment:
    """Points assigned to model planes: `index` `(A,)` into the points, `normal` `(A, 3)` unit
    plane normals, `offset` `(A,)` with the plane `normal · X = offset` (model CRS, metres),
    `polygon` `(A,)` indices into `SceneMesh.polygon_ids`."""

    index: np.ndarray
    normal: np.ndarray
    offset: np.ndarray
    polygon: np.ndarray

    def distances(self, X: np.ndarray) -> np.ndarray:
        """`(A,)` signed distances of the assigned points of `X` `(K, 3)` to their planes."""
        return np.einsum("ni,ni->n", X[self.index], self.normal) - self.offset


@dataclass(frozen=True, eq=False)
class PlaneFit:
    """Result of `fit_planes`: `correction` (`model_from_placed`), the assignment of the last
    round, point-to-plane RMS (m) of the assigned points before and after, the `(7, 7)`
    covariance of `(ω [rad], τ [m], σ)`, and the number of distinct planes used."""

    correction: Similarity
    assignment: PlaneAssignment
    rms_before_m: float
    rms_after_m: float
    covariance: np.ndarray
    planes: int


def local_normals(X: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per point of `X` `(K, 3)` the PCA normal `(K, 3)` of its `k` nearest points and whether
    the neighbourhood is planar `(K,)` (smallest eigenvalue < 10 % of the middle one)."""
    K = len(X)
    if K < 4:
        return np.zeros((K, 3)), np.zeros(K, bool)
    _, nb = cKDTree(X).query(X, k=min(k, K))
    D = X[nb] - X[nb].mean(axis=1, keepdims=True)
    w, V = np.linalg.eigh(np.einsum("nki,nkj->nij", D, D))
    return V[:, :, 0], w[:, 0] < 0.1 * np.maximum(w[:, 1], 1e-12)


def assign_planes(
    X: np.ndarray, centers: np.ndarray, caster: RayCaster, options: ReconstructionOptions
) -> PlaneAssignment:
    """Assign points `X` `(K, 3)` (model CRS) seen from camera centres `centers` `(K, 3)` to the
    model planes their rays hit (module docstring)."""
    d = X - centers
    rng = np.linalg.norm(d, axis=1)
    d = d / np.maximum(rng, 1e-12)[:, None]
    hits = caster.cast(centers, d)
    normal, planar = local_normals(X, options.normal_neighbours)
    n_poly = caster.mesh.polygon_normals[np.maximum(hits.polygon, 0)]
    cos = np.abs(np.einsum("ni,ni->n", normal, n_poly))
    ok = (
        hits.hit
        & (np.abs(hits.t - rng) < options.plane_max_distance_m)
        & (~planar | (cos >= np.cos(np.radians(options.plane_max_angle_deg))))
    )
    idx = np.flatnonzero(ok)
    hit_pt = centers[idx] + hits.t[idx, None] * d[idx]
    n = n_poly[idx]
    return PlaneAssignment(idx, n, np.einsum("ni,ni->n", n, hit_pt), hits.polygon[idx])


def fit_planes(
    X: np.ndarray,
    centers: np.ndarray,
    caster: RayCaster,
    prior_sigma_m: float,
    prior_sigma_deg: float,
    scale_sigma: float,
    pivot: np.ndarray,
    options: ReconstructionOptions,
) -> PlaneFit | None:
    """The correction `model_from_placed` of placed points `X` `(K, 3)` (model CRS) observed from
    `centers` `(K, 3)` (module docstring), the correction's a-priori σ: shift `prior_sigma_m`,
    rotation `prior_sigma_deg`, log scale `scale_sigma`; None when fewer than `min_plane_points`
    are assigned. The correction turns and scales about `pivot` `(3,)`: the camera centres'
    mean, which the GNSS/INS placement pins (about the points' centroid instead, a correction
    of 0.6° of yaw 10 m from a facade would move the cameras sideways by 0.1 m, which the
    facade cannot see and the prior does not undo)."""
    c = np.asarray(pivot, dtype=np.float64)
    q = np.zeros(7)
    prior_w = (
        1.0 / np.r_[np.full(3, np.radians(prior_sigma_deg)), np.full(3, prior_sigma_m), scale_sigma] ** 2
    )
    first: PlaneAssignment | None = None
    a = None
    N = np.zeros((7, 7))
    for _ in range(options.plane_rounds):
        S = similarity_about(q, c)
        a = assign_planes(S.points(X), S.scale * centers @ S.R.T + S.t, caster, options)
        if len(a.index) < options.min_plane_points:
            return None
        first = first or a
        q, N = _gauss_newton(q, c, X[a.index], a, prior_w, options.plane_loss_m)
    assert a is not None and first is not None
    S = similarity_about(q, c)
    before, after = first.distances(X), a.distances(S.points(X))
    r2 = after**2
    sigma2 = max(float(np.mean(np.minimum(r2, options.plane_loss_m**2 * 9))), 1e-6)
    return PlaneFit(
        correction=S,
        assignment=a,
        rms_before_m=float(np.sqrt(np.mean(before**2))),
        rms_after_m=float(np.sqrt(np.mean(r2))),
        covariance=np.linalg.inv(N / sigma2 + np.diag(prior_w)),
        planes=len(np.unique(a.polygon)),
    )


def normals_span(normals: np.ndarray) -> float:
    """Smallest eigenvalue of the mean `n_h n_hᵀ` of the horizontal parts `(A, 2)` of unit
    normals `(A, 3)` (model CRS, z up): the share of the distances that constrains the least
    constrained horizontal shift (0: one facade, or parallel ones, leave a direction open; 1/2
    for two orthogonal facades seen equally). The height is left out: on a drive walls are
    what the frames see, and the GNSS/INS height is what the placement keeps."""
    if len(normals) == 0:
        return 0.0
    h = np.asarray(normals, dtype=np.float64)[:, :2]
    return max(float(np.linalg.eigvalsh(h.T @ h / len(h))[0]), 0.0)


def _gauss_newton(
    q: np.ndarray,
    c: np.ndarray,
    X: np.ndarray,
    a: PlaneAssignment,
    prior_w: np.ndarray,
    loss_m: float,
    iterations: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """Huber-IRLS Gauss–Newton of the plane distances of `X` `(A, 3)` (assigned in `a`'s order)
    and the prior on `q`; returns `q` and the weighted `JᵀWJ` `(7, 7)` of the distances (m⁻²·m²)."""
    JtJ = np.zeros((7, 7))
    for _ in range(iterations):
        S = similarity_about(q, c)
        Y = S.scale * (X - c) @ S.R.T  # rotated, scaled offsets from the centroid
        r = np.einsum("ni,ni->n", Y + c + q[3:6], a.normal) - a.offset
        J = np.concatenate(
            [np.cross(Y, a.normal), a.normal, np.einsum("ni,ni->n", Y, a.normal)[:, None]], axis=1
        )
        w = np.minimum(1.0, loss_m / np.maximum(np.abs(r), 1e-12))
        JtJ = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r + prior_w * loss_m**2 * q
        step = np.linalg.solve(JtJ + np.diag(prior_w * loss_m**2), -g)
        q = q + step
        if np.max(np.abs(step)) < 1e-9:
            break
    return q, JtJ
