"""Which frames the sequence calibration (`calibration`) looks at, and where its start is searched.

In: the frames of a sequence in recording order, their GNSS/INS prior camera poses (world = model
CRS), a `FrameWireframes` over the scene and its `RayCaster`, a `Camera`, options. Out: a
`FrameSample`: the looked-at frames whose prior view shows scene edges (with how many edge
samples each shows), the frames that take part (`pick`), and the frame sets the start (one
common correction, `common_correction.joint_fit`) is searched on, in turn.

The cost is bounded whatever the sequence length: at most `look_frames` evenly spread frames are
looked at (one visibility each), at most `max_frames` take part, each the frame of its stretch
of the sequence that shows the most scene edges (well spread, and seeing the model well), and
every start set holds at most `start_frames` of them.

Start sets: one common correction `(ω, b)` holds over frames whose camera rotation differs
little (a lever-arm error `l` moves the camera by `(R_i − R_j) l` between frames i and j, which
the common correction does not model). The looked-at frames are cut into stretches of
consecutive frames whose rotation stays within `start_turn_deg` of the stretch's first frame.
One stretch (a straight drive, a flight line): the picked frames first, then `start_segments`
consecutive parts of the looked-at frames (a long drive's start where the whole does not fit).
Several (a drive with turns): the first `start_segments` stretches of at least `min_start_frames`
looked-at frames, in recording order (a whole-drive attempt would fail there, at the cost of a
stretch's); when fewer than `start_segments` are that long (a drive that turns often), the
longest of the shorter stretches of at least `min_short_frames` fill up the sets, longest first.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_log
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.edge_observations import FrameWireframes
from workers.pipeline.orientation.wireframe import EdgeOptions

__all__ = ["FrameSample", "SampleOptions", "sample_frames", "spread", "start_sets", "stretches"]


@dataclass(frozen=True)
class SampleOptions:
    """How many frames the calibration looks at and uses (see the module docstring)."""

    look_frames: int = 48
    max_frames: int = 24
    start_frames: int = 20
    start_segments: int = 3
    start_turn_deg: float = 45.0
    min_start_frames: int = 10
    # when fewer than `start_segments` stretches have `min_start_frames`, the longest of those with
    # at least this many looked-at frames fill up the start sets
    min_short_frames: int = 5
    # a looked-at frame counts when its prior view shows at least this many edge samples
    min_samples: int = 10


@dataclass(frozen=True)
class FrameSample:
    """The frames of a calibration (recording order).

    Attributes:
        looked: the frames looked at (at most `look_frames`).
        usable: those whose prior view shows at least `min_samples` scene edge samples.
        counts: `{frame: edge samples its prior view shows}` (not thinned: how much of the model it sees).
        pick: the frames that take part (at most `max_frames`).
    """

    looked: tuple[int, ...]
    usable: tuple[int, ...]
    counts: dict[int, int]
    pick: tuple[int, ...]


def spread(items: Sequence[int], n: int) -> list[int]:
    """At most `n` of `items`, evenly spread (first and last kept)."""
    if not items or n <= 0:
        return []
    k = np.unique(np.linspace(0, len(items) - 1, min(len(items), n)).round().astype(int))
    return [items[i] for i in k]


def sample_frames(
    frames: Sequence[int], priors: Mapping[int, Pose], wireframes: FrameWireframes, raycaster: RayCaster,
    edge_options: EdgeOptions, options: SampleOptions,
) -> FrameSample:
    """Look at evenly spread frames, keep those that show scene edges at their prior pose and pick
    the best-seeing frame of each of `max_frames` consecutive stretches of them."""
    frames = list(frames)
    looked = spread(frames, max(options.look_frames, options.max_frames))
    counts = {}
    for i in looked:
        vis = wireframes.visible(i, priors[i], raycaster, edge_options, 1 << 30)
        counts[i] = len(vis.points)
    usable = [i for i in looked if counts[i] >= options.min_samples]
    pick = []
    if usable:
        for part in np.array_split(np.arange(len(usable)), min(len(usable), options.max_frames)):
            best = max(part, key=lambda k: (counts[usable[k]], -k))
            pick.append(usable[int(best)])
    return FrameSample(tuple(looked), tuple(usable), counts, tuple(pick))


def stretches(frames: Sequence[int], priors: Mapping[int, Pose], turn_deg: float) -> list[list[int]]:
    """`frames` (recording order) cut into runs of consecutive frames whose prior camera rotation
    stays within `turn_deg` degrees of the run's first frame."""
    out: list[list[int]] = []
    ref = None
    for i in frames:
        R = priors[i].R_world_from_cam
        if ref is None or np.degrees(np.linalg.norm(so3_log(ref.T @ R))) > turn_deg:
            out.append([])
            ref = R
        out[-1].append(i)
    return out


def start_sets(sample: FrameSample, priors: Mapping[int, Pose], options: SampleOptions) -> list[list[int]]:
    """The frame sets the start is searched on, in turn (module docstring), each of at most
    `start_frames` frames."""
    usable = list(sample.usable)
    runs = stretches(usable, priors, options.start_turn_deg)
    if len(runs) <= 1:
        sets = [list(sample.pick)] + [[int(i) for i in part] for part in
                                      np.array_split(np.asarray(usable), max(options.start_segments, 1))]
    else:
        n = max(options.start_segments, 1)
        sets = [r for r in runs if len(r) >= options.min_start_frames][:n]
        # a drive that turns often (every stretch shorter than `min_start_frames`; the 300-frame
        # NRW drive of seed 2: stretches of 2-9 of the 48 looked-at frames) still gets a start:
        # its longest stretches of at least `min_short_frames`, longest first
        short = [r for r in runs if options.min_short_frames <= len(r) < options.min_start_frames]
        sets += sorted(short, key=lambda r: -len(r))[: n - len(sets)]
    return [spread(s, options.start_frames) for s in sets if s]
