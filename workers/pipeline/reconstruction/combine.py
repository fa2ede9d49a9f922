"""The reconstruction's poses in the form the building units take (`SequenceOrientation`), alone
(`--orientation sfm`) or combined with the model-edge sequence orientation (`both`): a frame the
edge path oriented (its blocks confirmed it by model edges, planes and priors) keeps that pose
where the reconstruction agrees with it (its points of the frame projected with both poses
within `max_disagreement_px`); a frame it left unoriented or rejected, or where the two
disagree, takes the reconstruction's, where registered.

Why the disagreement test: on the bench's homogeneous facades the edge path's acceptance took
the frames at 2–10 px median (roof lines and block outlines fit poses off by about the
calibrated priors' error), where the reconstruction, coregistered to the facade planes and, for
the height, to the model edges (`edge_placement`), reaches 0.34 px (seed 1, 40 and 60 frames);
there the two disagree by 0.5–9 px per frame (median 3.0 on 40 frames); on textured facades by
0.4–1.8 px (median 0.8: the reconstruction's own error grows along the drive, 0.88 px; edges:
0.28 px). The test is per edge block (median over its frames), as the edge path accepts per
block; the threshold (2 px) sits between those two scenes. The reconstruction overrides only
where the model fixes its placement (`ReconstructionOrientation.determined`: edges confirm it,
and facades of two orientations fix the horizontal, or on a single facade the edges in view
fix its in-plane shift, height and scale): a drive along one facade with a single vertical
corner in view leaves the shift along the line of sight to the GNSS/INS (bench seed 2: 4.5 px,
the edge path 0.4 px on those frames), and there the edges stay.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.sequence import SequenceOrientation
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.orient import ReconstructionOrientation, orient_reconstruction


def to_sequence(ro: ReconstructionOrientation) -> SequenceOrientation:
    """`ro` as a `SequenceOrientation` (no blocks; the registered frames are the oriented ones)."""
    return SequenceOrientation(
        poses=dict(ro.poses),
        covariance=dict(ro.covariance),
        blocks=[],
        tracks=ro.tracks,
        ties=dict(ro.ties),
        tie_rms_px=dict(ro.tie_rms_px),
    )


def combine(
    edges: SequenceOrientation,
    ro: ReconstructionOrientation,
    camera: Camera,
    max_disagreement_px: float,
) -> tuple[SequenceOrientation, list[int], list[int]]:
    """`edges` with the frames it did not orient taken from `ro` where registered, and the frames
    of every accepted edge block whose reconstruction placement the model fixed
    (`ReconstructionOrientation.determined`; module docstring) where the two disagree there by
    more than `max_disagreement_px` (median over those frames of the block). Returns the
    combination, the frames taken because the edge path left them, and those taken because the
    poses disagreed."""
    left = [f for f in ro.registered if f not in edges.covariance and f in edges.poses]
    both = [f for f in ro.registered if f in edges.covariance]
    d = {f: disagreement_px(camera, ro, f, edges.poses[f]) for f in both}
    spans = [tuple(b["frames"]) for b in edges.blocks if b.get("accepted")] or [
        (min(d, default=0), max(d, default=0))
    ]
    disagree: set[int] = set()
    for a, b in spans:
        # only where the model fixes the reconstruction's placement does it override the edges
        # (one facade, or parallel ones, without edges fixing the rest leave a shift to the GNSS/INS)
        block = [f for f in both if a <= f <= b and f in ro.determined]
        if block and float(np.median([d[f] for f in block])) > max_disagreement_px:
            disagree.update(block)
    taken = sorted(set(left) | disagree)
    poses, cov = dict(edges.poses), dict(edges.covariance)
    ties, rms = dict(edges.ties), dict(edges.tie_rms_px)
    for f in taken:
        poses[f], cov[f] = ro.poses[f], ro.covariance[f]
        ties[f], rms[f] = ro.ties[f], ro.tie_rms_px[f]
    extra = ro.tracks.subset(np.isin(ro.tracks.frame, taken))
    combined = SequenceOrientation(
        poses=poses,
        covariance=cov,
        blocks=edges.blocks,
        tracks=Tracks.concat([edges.tracks, extra]),
        ties=ties,
        tie_rms_px=rms,
        prior_noise=edges.prior_noise,
    )
    return combined, left, sorted(disagree)


def disagreement_px(camera: Camera, ro: ReconstructionOrientation, frame: int, pose: Pose) -> float:
    """RMS distance (px) between the frame's reconstructed points (model CRS) projected with the
    reconstruction's pose and with `pose`; 0 when the frame has none in front of both."""
    X = ro.tracks.point[ro.tracks.track[ro.tracks.frame == frame]]
    a, za = ro.poses[frame].project(camera, X)
    b, zb = pose.project(camera, X)
    ok = (za > 0) & (zb > 0)
    return float(np.sqrt(np.mean(np.sum((a[ok] - b[ok]) ** 2, axis=1)))) if ok.any() else 0.0


def with_reconstruction(
    method: str,
    edges: SequenceOrientation | None,
    camera: Camera,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    prior: Mapping[int, Pose],
    times: Mapping[int, float],
    accuracy: Accuracy | None,
    options: ReconstructionOptions = ReconstructionOptions(),
) -> tuple[SequenceOrientation, dict]:
    """The orient stage's result for `method` (`RunOptions.orientation`): `"edges"` returns
    `edges` as it is, `"sfm"` the reconstruction alone, `"both"` their combination (`combine`).
    Returns the orientation and the `report.json` `sequence_orientation` entries it adds:
    `method` and, with a reconstruction, `reconstruction` (`ReconstructionOrientation.to_dict`
    and, for `both`, `frames_from_reconstruction`). The other arguments: `orient_reconstruction`."""
    if method == "edges":
        if edges is None:
            raise ValueError("orientation 'edges' needs the edge path's result")
        return edges, {"method": method}
    ro = orient_reconstruction(camera, raycaster, frames, frame_source, prior, times, accuracy, options)
    if method == "sfm":
        return to_sequence(ro), {"method": method, "reconstruction": ro.to_dict()}
    if method != "both" or edges is None:
        raise ValueError(f"orientation {method!r} (edge result given: {edges is not None})")
    so, left, disagree = combine(edges, ro, camera, options.max_disagreement_px)
    figures = {**ro.to_dict(), "frames_left_by_edges": len(left), "frames_disagreeing": len(disagree)}
    return so, {"method": method, "reconstruction": figures}
