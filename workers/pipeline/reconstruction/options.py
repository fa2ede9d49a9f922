"""Parameters of the reconstruction-based orientation (`orient.orient_reconstruction`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from workers.pipeline.orientation.tracks import TrackOptions


@dataclass(frozen=True)
class ReconstructionOptions:
    """Parameters of Hoegner & Stilla's method 1 (metres, degrees, pixels, seconds).

    Attributes:
        tracks: the LK tracker's options (`orientation.tracks.track_sequence`).
        min_observations_per_frame, low_texture_ratio: when half of the run's frames or more
            have fewer observations than this, the run is tracked again with the tracker's
            salience ratio lowered to `low_texture_ratio` (a per-frame test: on the homogeneous
            bench drive of seed 2 the mean, 19 per frame, hid that 30 of 40 frames had fewer
            than 15 and 23 frames went unregistered); on a facade textured all over (render, brick) the
            frame's median texture is the facade's own and 10 × it found no point at all on the
            homogeneous bench scene (3: 119 tracks on 12 frames, all within 1 px of the truth);
            on facades with windows the lower ratio adds weaker, less reliable tracks (a facade
            walk: σ0 0.66 px instead of 0.11), so it is the fallback, not the default.
        max_gap_s: a time step longer than this splits the sequence into separate
            reconstructions (tracks do not survive a gap).
        start_smoothing_s, noisy_factor, frame_sigma_m, frame_sigma_deg: the start poses of
            tracking and triangulation are the priors smoothed over `start_smoothing_s` (Gaussian
            σ, seconds) when the priors' white noise (`smoothing.prior_noise`) exceeds
            `noisy_factor` × (`frame_sigma_m`, `frame_sigma_deg`); else the priors themselves.
        min_track_length: observations a track needs to be triangulated.
        min_depth_m: a triangulated point closer than this to (or behind) a camera observing it
            is dropped (an ill-conditioned intersection).
        min_angle_deg: smallest largest-angle between the rays of a track to triangulate it.
        ba_loss_px: scale of the Cauchy loss of pycolmap's bundle adjustment (px).
        ba_iterations: its iteration limit; `ba_rounds`: adjustments, each after dropping the
            observations beyond `max_reprojection_px` of the previous one.
        max_reprojection_px: an observation beyond this after an adjustment is dropped.
        max_sigma0_px: a reconstruction whose reprojection σ0 exceeds this is rejected.
        min_frame_points: a frame needs this many adjusted points to count as registered.
        min_shared_points: frames sharing this many points belong to the same connected part;
            each part is placed on its own (`colmap.components`).
        placement_loss_m: Huber scale of the camera centres' fit to the GNSS/INS positions.
        plane_max_distance_m, plane_max_angle_deg: a point is assigned to the model plane its
            observing ray hits when it lies within this distance of it along the ray and its
            local normal (PCA of `normal_neighbours` nearest points) lies within this angle of
            the plane's normal (points whose neighbourhood is not planar keep the ray's test only).
        plane_loss_m: soft-L1 scale of the point-to-plane distances.
        plane_rounds: assignment + fit rounds.
        min_plane_points: fewer assigned points leave the GNSS/INS placement as it is.
        scale_sigma: floor of the a-priori σ of the placement's log scale (its own standard error
            from the camera centres is used where larger: planes that meet in one point leave
            the scale to the GNSS/INS).
        prior_sigma_m, prior_sigma_deg: a-priori σ of the placement's shift and rotation when the
            accuracy of the priors is not given.
        max_disagreement_px: `--orientation both`: a frame the edge path oriented takes the
            reconstruction's pose where the two disagree by more than this (px, median over
            the frames of its edge block; `combine`) and the reconstruction's facades fixed
            both horizontal shift directions there and the edges confirm its height. With the
            edge placement the reconstruction's own error fell (bench seed 1, 40 frames:
            textured 0.88 px median, disagreeing with the edge path's 0.28 px by 0.8 px median
            per frame, at most 1.8; homogeneous: 0.34 px against the edge path's 2.1 px, 3.0
            px median disagreement), so 5 px left the homogeneous scene to the edges.
        plane_adjustment: after the facade coregistration, adjust poses and points once more
            with the ties, the assigned points' plane distances (σ `plane_sigma_m`) and the
            priors (common error of the accuracy's σ, per-frame noise of `frame_sigma_deg`,
            `frame_sigma_m`) (`plane_adjust.adjust_on_planes`); its result is kept when the
            adjustment converged and the ties' RMS stays within `plane_adjust_max_sigma0_px`.
            Only where the facades fix both horizontal shift directions (`min_normal_spread`):
            on one facade the adjustment leaves the in-plane shift, the scale and the turn about
            the normal to the per-frame priors, which bend the block instead (the one-facade
            walk of `tests/unit/test_reconstruction_sfm.py`: max 3.6 → 5.1 px).
        plane_sigma_m: σ of a point's distance from its model plane in that adjustment.
        plane_adjust_tie_sigma_px: σ of a tie observation there (Huber at twice it).
        min_normal_spread: the facades fix both horizontal shift directions when the smallest
            eigenvalue of the assigned points' mean horizontal `n nᵀ` reaches this
            (`planes.normals_span`).
        edge_placement: after the facade coregistration (and the plane adjustment), correct the
            part's similarity by the model edges its frames see (`edge_placement.fit_on_edges`:
            the height walls leave open, a single facade's in-plane shift, turn and scale), tied
            to what the planes fixed by the plane fit's information.
        edge_frames: at most this many frames (evenly along the part) observe the edges;
            `edge_min_frames`: fewer frames with visible edges leave the placement as it is.
        edge_iterations, edge_radius_start_px, edge_radius_decay: Gauss-Newton iterations, the
            edge search radius at the start (px) and its shrink per iteration (to the frame
            fit's minimum, `FrameFitOptions.edge_radius_min_px`).
        edge_coarse_min_sigma_m, edge_coarse_max_m, edge_coarse_step_m, edge_coarse_downsample,
        edge_coarse_blur, edge_coarse_min_gain: the grid search of the block's shift before
            the Gauss-Newton fit (`edge_placement.coarse_shift`): along the shift directions
            whose a-priori σ exceeds the first, ±3σ up to the second, in steps of the third
            (metres), on gradients downsampled and blurred by the next two (pixels), kept when
            it raises the oriented-gradient score by `edge_coarse_min_gain` per frame; at most
            `edge_coarse_max_candidates` shifts (coarser steps where three directions are open).
        edge_min_gain: the correction is kept when the frames' edge support (share of samples
            within `FrameFitOptions.support_px` of an image edge) rises by at least this (the
            one-wall walk of `tests/unit/test_reconstruction_sfm.py` starts at support 1.0: a
            correction there only moved the poses within the edges' noise); or, with the
            support falling by at most `edge_max_support_loss`, when the mean offset of the
            samples that found an edge falls by the share `edge_min_offset_gain` (the support
            counts samples within 1.5 px and misses sub-pixel errors: bench seed 1, 60-frame
            homogeneous drive, a block 0.042 m low, support 0.766 -> 0.759, offset 0.331 ->
            0.288 px; kept: pairs below 1 px 0.344 -> 0.926).
        edge_min_support, edge_max_shift_sigma_m: a part's placement counts as determined
            (`ReconstructionOrientation.determined`, where `both` may override the edge path)
            when its final edge support reaches the first and either its facades fix the
            horizontal or planes and edges fix every shift direction to the second (σ, metres;
            bench seed 3, one facade with its corners in view: 0.044 m, 0.47 px median; seed 2,
            one facade and one vertical corner: 0.098 m, 4.5 px, the edge path 0.4 px there).
    """

    tracks: TrackOptions = field(default_factory=TrackOptions)
    min_observations_per_frame: float = 15.0
    low_texture_ratio: float = 3.0
    max_gap_s: float = 1.0
    start_smoothing_s: float = 1.0
    noisy_factor: float = 1.5
    frame_sigma_m: float = 0.3
    frame_sigma_deg: float = 0.3
    min_track_length: int = 3
    min_depth_m: float = 0.5
    min_angle_deg: float = 0.5
    ba_loss_px: float = 1.0
    ba_iterations: int = 100
    ba_rounds: int = 2
    max_reprojection_px: float = 3.0
    max_sigma0_px: float = 2.0
    min_frame_points: int = 8
    min_shared_points: int = 5
    placement_loss_m: float = 0.5
    plane_max_distance_m: float = 1.0
    plane_max_angle_deg: float = 20.0
    normal_neighbours: int = 8
    plane_loss_m: float = 0.05
    plane_rounds: int = 3
    min_plane_points: int = 20
    scale_sigma: float = 0.001
    prior_sigma_m: float = 1.0
    prior_sigma_deg: float = 1.0
    max_disagreement_px: float = 2.0
    min_normal_spread: float = 0.02
    plane_adjustment: bool = True
    plane_sigma_m: float = 0.05
    plane_adjust_tie_sigma_px: float = 0.15
    plane_adjust_max_sigma0_px: float = 1.0
    edge_placement: bool = True
    edge_frames: int = 20
    edge_min_frames: int = 3
    edge_iterations: int = 8
    edge_radius_start_px: float = 16.0
    edge_radius_decay: float = 0.75
    edge_min_gain: float = 0.01
    edge_min_offset_gain: float = 0.05
    edge_max_support_loss: float = 0.02
    edge_min_support: float = 0.5
    edge_max_shift_sigma_m: float = 0.06
    edge_coarse_min_sigma_m: float = 0.05
    edge_coarse_max_m: float = 1.0
    edge_coarse_step_m: float = 0.04
    edge_coarse_downsample: int = 2
    edge_coarse_blur: float = 1.0
    edge_coarse_min_gain: float = 0.02
    edge_coarse_max_candidates: int = 3000

    def __post_init__(self) -> None:
        if self.min_track_length < 2 or self.ba_rounds < 1 or self.plane_rounds < 1:
            raise ValueError("min_track_length >= 2, ba_rounds >= 1 and plane_rounds >= 1 required")
