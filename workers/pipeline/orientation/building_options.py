"""Parameters of the per-building orientation (`building.refine_building`), and their variant for
calibrated priors.

`CoregisterOptions` holds the options of every stage a building's orientation runs (features,
wireframe, frame fit, joint coarse search, joint fit, block orientation, sequence level,
inheritance, scene fallback; the steps are numbered as in `building`), the prior's standard
deviations (`priors.prior_information`) and the per-frame deviation (`priors.PriorOptions`).
`calibrated_options` turns them into the options for priors from an accepted sequence
calibration (`calibration`). Both are importable from `building` too.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from workers.pipeline.orientation.block import BlockOptions
from workers.pipeline.orientation.common_correction import JointOptions
from workers.pipeline.orientation.features import FeatureOptions
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.priors import PriorOptions
from workers.pipeline.orientation.wireframe import EdgeOptions

__all__ = ["CoregisterOptions", "calibrated_options"]


@dataclass(frozen=True)
class CoregisterOptions:
    """All parameters of the per-building orientation."""

    # image features (Förstner, LSD, intersections, edge distance pyramid)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    # model wireframe and its visibility
    edges: EdgeOptions = field(default_factory=EdgeOptions)
    # per-frame adjustment and acceptance
    fit: FrameFitOptions = field(default_factory=FrameFitOptions)
    # a-priori standard deviations when the manifest has no `accuracy` (metres, degrees)
    default_position_sigma_m: float = 2.0
    default_attitude_sigma_deg: float = 1.0
    # the prior's standard deviations are multiplied by this and floored (the manifest's accuracy
    # does not cover the unknown boresight misalignment of several degrees)
    prior_sigma_scale: float = 2.0
    position_sigma_floor_m: float = 1.0
    attitude_sigma_floor_deg: float = 2.0
    # sequence level: time window (seconds) and Gaussian time scale of the neighbour prediction;
    # without times, frame indices are used as seconds
    window_s: float = 4.0
    time_sigma_s: float = 1.5
    # joint coarse search over all frames of the building (common boresight/position error) ...
    joint_coarse: bool = True
    # ... at most this many frames (evenly spread) take part ...
    joint_coarse_max_frames: int = 16
    # ... on this pyramid level (full-resolution pixels per level pixel; the frames are first
    # downsampled by `joint_coarse_downsample`), over image shifts up to this radius (pixels;
    # model samples up to this far outside the frame take part) and these depth offsets (shares
    # of the median depth)
    joint_coarse_level: int = 8
    joint_coarse_downsample: int = 2
    joint_coarse_radius_px: float = 320.0
    joint_coarse_depth_steps: tuple[float, ...] = (0.0,)
    # ... with the wireframe of the whole scene of the ray caster (the building and its
    # neighbours: a row of similar houses is no longer ambiguous) or of the building alone ...
    joint_coarse_scene: bool = True
    # ... the minimum must lower the typical mean edge distance by this share, else no joint
    # correction is applied and every frame searches on its own ...
    joint_coarse_min_gain: float = 0.35
    # ... up to this many distinct minima, verified by the fine stage on `verify_frames` frames
    # with the scene wireframe (the best confirmed one is applied) ...
    joint_coarse_candidates: int = 3
    verify_frames: int = 3
    # ... and rolls about the optical axis (degrees; boresight errors of several degrees)
    joint_coarse_rolls_deg: tuple[float, ...] = (-8.0, -6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0, 8.0)
    # per-frame coarse search radius after the joint one, pixels (0: none; the per-frame search
    # sees one building only and may jump to a similar neighbour)
    frame_coarse_radius_px: float = 0.0
    # when the joint coarse search finds no distinct minimum (close-range drives: vertical
    # corners, window rows), ONE common correction of all frames is adjusted from the stacked
    # edge observations of every frame against the scene wireframe (`common_correction`); when
    # accepted, pass 1 is centred on it, and a frame still at its prior takes the jointly
    # corrected pose with status "refined" when its own edge support there reaches
    # `fit.min_support` and the joint uncertainty projected onto the building is
    # ≤ `joint_max_sigma_px` (the common part of the error is then known; what a frame alone
    # cannot observe of its own white noise stays, e.g. the height of a frame that sees only
    # vertical corners)
    joint_fine: bool = True
    joint_max_sigma_px: float = 3.0
    joint: JointOptions = field(default_factory=JointOptions)
    # close-range drives: the building's frames oriented as one block (feature tracks and a
    # bundle adjustment with the model: `block`) from the calibrated priors or from
    # the joint correction, or taken from the sequence orientation when it ran (step 0b); when
    # the block is rejected, the frames go on one by one. Off: neither
    block_orientation: bool = True
    block: BlockOptions = field(default_factory=BlockOptions)
    # frames whose sequence pose the building's edges do not confirm (step 0b keeps their priors)
    # are oriented on their own by the steps below (flights: `job.plan` sets it; a frame there
    # sees enough buildings to orient alone, unlike a close-range drive frame)
    sequence_fallback: bool = False
    # per-frame deviation of a frame's correction from its neighbours' and from the common
    # correction (white noise, vibration), and the null shift of the edge-support test: one
    # `PriorOptions` for the frames, the joint fit and the block orientation
    prior: PriorOptions = field(default_factory=PriorOptions)
    # neighbours further than this (Mahalanobis², per degree of freedom) from the prediction are
    # outliers; an accepted frame this far from its prediction is refitted
    outlier_gate: float = 9.0
    # the regulariser of the prediction: this share of the prior's information
    prediction_regulariser: float = 0.05
    # inheritance of the neighbours' correction (see the module docstring)
    inherit_min_neighbours: int = 3
    inherit_max_sigma_px: float = 1.0
    # run the sequence level (second pass, inheritance) at all ...
    sequence: bool = True
    # ... and only when at least this many frames converged in pass 1 (else there is nothing
    # to predict from)
    min_converged_frames: int = 2
    # frames still at their prior are oriented (passes 1, 2, inheritance) against the whole
    # scene of the ray caster, the building and its neighbours
    scene_fallback: bool = True
    # the priors come from an accepted sequence calibration (`calibration`): the common error is
    # already removed, so no joint coarse search and no coarse search of the joint fine stage
    calibrated: bool = False
    # ... then the joint adjustment runs only when fewer than this share of a probe of frames
    # (evenly spread) is refined on its own
    calibrated_joint_below: float = 0.5
    calibrated_probe_frames: int = 5


def calibrated_options(options: CoregisterOptions, accuracy_floor_m: float = PriorOptions.frame_sigma_m,
                       accuracy_floor_deg: float = PriorOptions.frame_sigma_deg) -> CoregisterOptions:
    """`options` for priors from an accepted sequence calibration: no joint coarse search and a
    narrow one in the joint fine stage, the prior's σ floors lowered to the per-frame deviations
    (metres, degrees; default: those of `PriorOptions`)."""
    # a narrow joint search stays: a calibration from a short sequence can leave a degree of pan
    # (drives: pan and a lateral offset are nearly interchangeable along one street)
    joint = replace(options.joint, coarse_radius_px=64.0, translation_max_m=1.0, translation_step_m=0.5,
                    candidates=1, translation_candidates=1)
    return replace(options, calibrated=True, joint_coarse=False, joint=joint,
                   prior_sigma_scale=1.0, position_sigma_floor_m=accuracy_floor_m,
                   attitude_sigma_floor_deg=accuracy_floor_deg)
