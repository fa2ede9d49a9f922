"""Reconstruction-based orientation (Hoegner & Stilla, method 1): the TIR sequence's own
structure from motion, placed on the GNSS/INS and coregistered to the model's facades.

In: `Camera`, a `RayCaster` over the buildings near the cameras, the frames in recording order
with their times (seconds), a `FrameSource`, the (calibrated) prior pose per frame (world =
model CRS) with its a-priori `Accuracy`, `ReconstructionOptions`.
Out: `ReconstructionOrientation`: per registered frame the corrected pose and a covariance of
`(ω_cam [rad], dC_world [m])`, the others keep their prior; the figures of `report.json`.

Per run of frames without a gap longer than `max_gap_s`: the LK tracks of the sequence
orientation (`orientation.tracks.track_sequence`, from the priors or, when they are noisy, the
smoothed priors) → triangulation from those poses and pycolmap's bundle adjustment
(`colmap.reconstruct`) → the 7-parameter similarity onto the GNSS/INS (`similarity.place_on_priors`:
rotation from the attitudes, scale and shift from the centres) → the reconstructed points
assigned to the model's facade planes and the similarity corrected by their distances
(`planes.fit_planes`) → every registered frame's pose through the final similarity → the block
adjusted once more with the facade points held to their planes and the priors as a common
error plus per-frame noise (`plane_adjust.adjust_on_planes`: what bent the block, one similarity
cannot remove; where the facades fix both horizontal directions, `options.plane_adjustment`) →
the part's similarity corrected by the model edges its frames see (`edge_placement.fit_on_edges`:
the height walls leave to the GNSS/INS, and on a single facade its in-plane shift, turn and
scale where the frames show edges; `options.edge_placement`).

Why the LK tracks and not pycolmap's SIFT: on the one-facade sequence (`bench/orientation_sfm.py`,
`features_on_tir`, 40 frames) the LK tracks give 1013 observations of which 875 lie within 1 px
of the truth (98.6 % of the later observations); SIFT on CLAHE-stretched 8-bit copies, matched
between consecutive frames (ratio 0.8), gives 7195 matches of which 3177 lie within 1 px (44 %):
more correct pairs, but two-view pairs amid a majority of wrong ones (the regular window grid),
which would need geometric verification and track building before a reconstruction; the LK
tracker does both already (its essential-matrix RANSAC, its tracks over up to 12 frames).
Facades textured all over defeat the tracker's salience test; the run is then tracked again at
a lower ratio (`ReconstructionOptions.low_texture_ratio`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import project_jacobian
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.smoothing import prior_noise, smooth_poses
from workers.pipeline.orientation.tracks import Tracks, track_sequence
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe, WireframeError, mesh_wireframe
from workers.pipeline.reconstruction.colmap import Adjusted, components, reconstruct
from workers.pipeline.reconstruction.edge_placement import EdgePlacement, fit_on_edges
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.plane_adjust import adjust_on_planes
from workers.pipeline.reconstruction.planes import fit_planes, normals_span
from workers.pipeline.reconstruction.similarity import Similarity, place_on_priors


@dataclass(frozen=True, eq=False)
class ReconstructionOrientation:
    """Result of `orient_reconstruction`.

    Attributes:
        poses: `{frame: Pose}` of every frame: corrected where registered, else the prior.
        covariance: `{frame: (6, 6)}` of `(ω_cam, dC_world)` of the registered frames.
        tracks: the kept observations with their points in the model CRS.
        ties, tie_rms_px: per registered frame its observations and their reprojection RMS (px).
        runs: per run of frames its figures (`to_dict`).
        determined: registered frames whose part's final placement the model edges confirm
            (`edge_placement`: support of at least `edge_min_support`, the height) and whose
            facade coregistration fixed both horizontal shift directions (facades of two
            orientations: `facades_fix_horizontal`) or, on one facade, whose edges fixed what
            it leaves open (`edge_max_shift_sigma_m`); the others keep the GNSS/INS
            placement's shift along what planes and edges leave open.
    """

    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    tracks: Tracks
    ties: dict[int, int] = field(default_factory=dict)
    tie_rms_px: dict[int, float] = field(default_factory=dict)
    runs: list[dict] = field(default_factory=list)
    determined: set[int] = field(default_factory=set)

    @property
    def registered(self) -> list[int]:
        """Frames the reconstruction registered, in index order."""
        return sorted(self.covariance)

    def to_dict(self) -> dict:
        """The `report.json` `reconstruction` block: frames, frames registered, tracks and their
        mean length, reprojection σ0 (px), point-to-plane RMS before/after (m), per run."""
        lengths = self.tracks.lengths()
        return {
            "frames": len(self.poses),
            "frames_registered": len(self.covariance),
            "tracks": int(self.tracks.n_tracks),
            "mean_track_length": round(float(lengths.mean()), 2) if len(lengths) else None,
            "runs": self.runs,
        }


class _LazyImages(Mapping[int, np.ndarray]):
    """`{frame: image}` loading from a `FrameSource` on access (a drive does not fit in memory)."""

    def __init__(self, source: FrameSource, frames: Sequence[int]) -> None:
        self._source, self._frames = source, list(frames)

    def __getitem__(self, f: int) -> np.ndarray:
        return self._source.load(int(f))

    def __iter__(self) -> Iterator[int]:
        return iter(self._frames)

    def __len__(self) -> int:
        return len(self._frames)


def runs(frames: Sequence[int], times: Mapping[int, float], max_gap_s: float) -> list[list[int]]:
    """`frames` split where the time step exceeds `max_gap_s`; runs of fewer than 3 frames dropped.

    >>> runs([0, 1, 2, 3, 4], {0: 0.0, 1: 0.1, 2: 0.2, 3: 5.0, 4: 5.1}, 1.0)
    [[0, 1, 2]]
    """
    out: list[list[int]] = []
    cur: list[int] = []
    for f in frames:
        if cur and times[f] - times[cur[-1]] > max_gap_s:
            out.append(cur)
            cur = []
        cur.append(int(f))
    out.append(cur)
    return [r for r in out if len(r) >= 3]


def orient_reconstruction(
    camera: Camera,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    prior: Mapping[int, Pose],
    times: Mapping[int, float],
    accuracy: Accuracy | None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> ReconstructionOrientation:
    """Orient the frames by their own reconstruction (module docstring); see `orient_sequence`
    for the arguments (`accuracy` gives the a-priori σ of the placement's shift and rotation)."""
    frames = [int(f) for f in frames]
    poses = {f: prior[f] for f in frames}
    cov: dict[int, np.ndarray] = {}
    ties: dict[int, int] = {}
    rms: dict[int, float] = {}
    parts: list[Tracks] = []
    determined: set[int] = set()
    figures: list[dict] = []
    sig_m = float(np.mean(accuracy.position_m)) if accuracy is not None else options.prior_sigma_m
    sig_deg = float(np.mean(accuracy.attitude_deg)) if accuracy is not None else options.prior_sigma_deg
    wf = _wireframe(raycaster) if options.edge_placement else None
    for run in runs(frames, times, options.max_gap_s):
        fig, placed_parts = _orient_run(
            camera, raycaster, wf, run, frame_source, prior, times, sig_m, sig_deg, options
        )
        figures.append(fig)
        for (placed, cov_run, tracks, fixed), adj in placed_parts:
            if fixed:
                determined.update(placed)
            for f, p in placed.items():
                poses[f], cov[f] = p, cov_run[f]
                e = adj.obs_error_px[adj.obs_frame == f]
                ties[f], rms[f] = len(e), float(np.sqrt(np.mean(e**2)))
            parts.append(tracks)
    return ReconstructionOrientation(poses, cov, Tracks.concat(parts), ties, rms, figures, determined)


def _wireframe(caster: RayCaster) -> Wireframe | None:
    """The scene's wireframe (model CRS; None when the mesh has none)."""
    try:
        return mesh_wireframe(caster.mesh, EdgeOptions())
    except WireframeError:
        return None


def _orient_run(
    camera: Camera,
    caster: RayCaster,
    wireframe: Wireframe | None,
    run: list[int],
    source: FrameSource,
    prior: Mapping[int, Pose],
    times: Mapping[int, float],
    sig_m: float,
    sig_deg: float,
    options: ReconstructionOptions,
) -> tuple[dict, list[tuple[tuple[dict[int, Pose], dict[int, np.ndarray], Tracks, bool], Adjusted]]]:
    """One run of frames: its figures and per connected part of its reconstruction ((poses,
    covariances, tracks), adjustment)."""
    deg, m = prior_noise(prior, run)
    noisy = options.start_smoothing_s > 0 and (
        deg > options.noisy_factor * options.frame_sigma_deg
        or m > options.noisy_factor * options.frame_sigma_m
    )
    start = (
        smooth_poses(prior, run, times, options.start_smoothing_s) if noisy else {f: prior[f] for f in run}
    )
    tracks = track_sequence(camera, run, _LazyImages(source, run), start, caster, options.tracks)
    seen, count = np.unique(tracks.frame, return_counts=True)
    per_frame = dict(zip(seen.tolist(), count.tolist(), strict=True))
    low = float(np.median([per_frame.get(f, 0) for f in run])) < options.min_observations_per_frame
    if low:  # a facade textured all over: nothing stands out of the frame's median texture
        weak = replace(options.tracks, min_texture_ratio=options.low_texture_ratio)
        tracks = track_sequence(camera, run, _LazyImages(source, run), start, caster, weak)
    fig: dict = {
        "frames": [run[0], run[-1]],
        "tracks": int(tracks.n_tracks),
        "smoothed_start": noisy,
        "low_texture_tracking": low,
    }
    origin = np.mean([start[f].center for f in run], axis=0)
    local = Similarity(1.0, np.eye(3), -origin)
    adj = reconstruct(camera, tracks, run, local.poses(start), options)
    if adj is None:
        return {**fig, "registered": 0, "reason": "too few triangulated points"}, []
    fig.update(
        registered=len(adj.poses),
        points=len(adj.points),
        mean_track_length=round(float(len(adj.obs_track) / max(len(adj.points), 1)), 2),
        reprojection_px_before_adjustment=round(adj.before_px, 3),
        sigma0_px=round(adj.sigma0_px, 3),
    )
    if not adj.sigma0_px <= options.max_sigma0_px:
        return {**fig, "registered": 0, "reason": f"reprojection σ0 {adj.sigma0_px:.2f} px"}, []
    parts = components(adj, options.min_shared_points)
    images = _LazyImages(source, run)
    fig["parts"] = [
        _place(camera, caster, wireframe, images, part, prior, origin, sig_m, sig_deg, options)
        for part in parts
    ]
    fig["registered"] = sum(len(p.poses) for p in parts)
    return fig, [(f.pop("_result"), part) for f, part in zip(fig["parts"], parts, strict=True)]


def _place(
    camera: Camera,
    caster: RayCaster,
    wireframe: Wireframe | None,
    images: Mapping[int, np.ndarray],
    adj: Adjusted,
    prior: Mapping[int, Pose],
    origin: np.ndarray,
    sig_m: float,
    sig_deg: float,
    options: ReconstructionOptions,
) -> dict:
    """One connected part (world = model CRS − `origin`) placed on the GNSS/INS and coregistered
    to the facades: its figures, with `"_result"`: (poses, covariances, tracks) in the model CRS."""
    rec_poses = dict(adj.poses)
    placement, sigma_scale = place_on_priors(
        rec_poses,
        {f: Pose(prior[f].R_world_from_cam, prior[f].center - origin) for f in rec_poses},
        options.placement_loss_m,
    )
    placed = placement.then(Similarity(1.0, np.eye(3), origin))
    X = placed.points(adj.points)
    first = {int(t): int(f) for t, f in zip(adj.obs_track[::-1], adj.obs_frame[::-1], strict=True)}
    centers = np.array([placed.pose(rec_poses[first[int(t)]]).center for t in adj.track_ids])
    sig_s = max(sigma_scale, options.scale_sigma)
    pivot = np.mean([placed.pose(p).center for p in rec_poses.values()], axis=0)
    fit = fit_planes(X, centers, caster, sig_m, sig_deg, sig_s, pivot, options)
    final = placed if fit is None else placed.then(fit.correction)
    out_poses = final.poses(rec_poses)
    Xm = final.points(adj.points)
    spread = 0.0 if fit is None else normals_span(fit.assignment.normal)
    spans = bool(spread >= options.min_normal_spread)
    pa = None
    if fit is not None and spans and options.plane_adjustment:
        pa = adjust_on_planes(
            camera, caster, adj, out_poses, Xm, fit.assignment, prior, sig_m, sig_deg, options
        )
        if pa is not None:
            out_poses, Xm = pa.poses, pa.points
    place_cov = np.zeros((6, 6)) if fit is None else _pose_block(fit.covariance)
    ep = None
    if wireframe is not None:
        info = np.diag(_prior_info(sig_m, sig_deg, sig_s)) if fit is None else np.linalg.inv(fit.covariance)
        ep = fit_on_edges(camera, caster, wireframe, out_poses, images, pivot, info, options)
        if ep is not None and ep.kept:
            out_poses, Xm = ep.correction.poses(out_poses), ep.correction.points(Xm)
            place_cov = _pose_block(ep.covariance)
    cov = {f: _resection_covariance(camera, p, Xm, adj, f) + place_cov for f, p in out_poses.items()}
    return {
        "frames": [min(rec_poses), max(rec_poses)],
        "registered": len(rec_poses),
        "points": len(adj.points),
        "sigma0_px": round(adj.sigma0_px, 3),
        "placement_scale": round(placement.scale, 4),
        "placement_scale_sigma": round(sigma_scale, 4),
        "planes": 0 if fit is None else fit.planes,
        "plane_points": 0 if fit is None else len(fit.assignment.index),
        "point_to_plane_rms_m_before": None if fit is None else round(fit.rms_before_m, 3),
        "point_to_plane_rms_m_after": None if fit is None else round(fit.rms_after_m, 3),
        "plane_adjustment": None if pa is None else pa.to_dict(),
        "edge_placement": None if ep is None else ep.to_dict(),
        "normal_spread": round(spread, 4),
        "facades_fix_horizontal": spans,
        "_result": (out_poses, cov, _tracks(adj, Xm), _determined(ep, spans, options)),
    }


def _determined(ep: EdgePlacement | None, spans: bool, options: ReconstructionOptions) -> bool:
    """Whether the part's placement is fixed by the model: the edges confirm it (edge support
    after the correction where kept, else before, of `edge_min_support` or more) and either
    facades of two orientations fix the horizontal shift (`spans`) or planes and edges together
    fix every shift direction within `edge_max_shift_sigma_m` (a single facade with the
    corners, eaves and ground lines in view)."""
    if ep is None:
        return False
    confirmed = (ep.support_after if ep.kept else ep.support_before) >= options.edge_min_support
    return confirmed and (spans or ep.shift_sigma_m <= options.edge_max_shift_sigma_m)


def _prior_info(sig_m: float, sig_deg: float, sig_s: float) -> np.ndarray:
    """`(7,)` a-priori information of a placement correction `(ω, τ, σ)` (rad⁻², m⁻², 1)."""
    return 1.0 / np.r_[np.full(3, np.radians(sig_deg)), np.full(3, sig_m), sig_s] ** 2


def _pose_block(c7: np.ndarray) -> np.ndarray:
    """The `(6, 6)` (ω, shift) block of the plane fit's `(7, 7)` covariance, as an isotropic
    bound per part (the similarity's ω is in world axes, a pose's in camera axes)."""
    w, t = np.max(np.diag(c7)[:3]), np.max(np.diag(c7)[3:6])
    return np.diag([w, w, w, t, t, t])


def _resection_covariance(camera: Camera, pose: Pose, X: np.ndarray, adj: Adjusted, f: int) -> np.ndarray:
    """`(6, 6)` covariance of `(ω_cam, dC_world)` of frame `f` from its observations of the
    adjusted points `X` `(K, 3)` (model CRS), σ0 the reconstruction's."""
    row = {int(t): k for k, t in enumerate(adj.track_ids)}
    sel = np.flatnonzero(adj.obs_frame == f)
    _, _, J = project_jacobian(camera, pose, X[[row[int(t)] for t in adj.obs_track[sel]]])
    N = np.einsum("nki,nkj->ij", J, J)
    return np.linalg.pinv(N) * max(adj.sigma0_px, 0.1) ** 2


def _tracks(adj: Adjusted, X: np.ndarray) -> Tracks:
    """The kept observations as `Tracks` with their points `X` (model CRS; normals unknown: 0)."""
    row = {int(t): k for k, t in enumerate(adj.track_ids)}
    track = np.array([row[int(t)] for t in adj.obs_track], dtype=np.int64)
    return Tracks(track, adj.obs_frame.copy(), adj.obs_uv.copy(), X, np.zeros_like(X), np.zeros(len(X)))
