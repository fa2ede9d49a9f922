"""The calibration's start sets (`calibration_frames.start_sets`) on drives that turn: a drive
that turns often (every stretch of the looked-at frames within `start_turn_deg` shorter than
`min_start_frames`, as the 300-frame NRW drive of seed 2) must still get start sets (before: none,
and the calibration was refused with "no common correction: no frame set")."""

from __future__ import annotations

import itertools

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_log
from workers.pipeline.orientation.calibration_frames import FrameSample, SampleOptions, start_sets


def turning_drive(stretch_lengths: list[int], turn_deg: float = 60.0) -> dict[int, Pose]:
    """Priors of a drive (frames 0..n-1) whose heading turns by `turn_deg` after each stretch of
    `stretch_lengths` frames (camera looking sideways, 1 m per frame)."""
    priors: dict[int, Pose] = {}
    k, heading, c = 0, 0.0, np.zeros(3)
    for n in stretch_lengths:
        for _ in range(n):
            a = np.radians(heading)
            # camera: x along the drive, z (optical axis) to its left, y down
            fwd, left = np.array([np.cos(a), np.sin(a), 0.0]), np.array([-np.sin(a), np.cos(a), 0.0])
            R = np.column_stack([fwd, np.cross(left, fwd), left])
            priors[k] = Pose(R, c.copy())
            c = c + fwd
            k += 1
        heading += turn_deg
    return priors


def sample_of(priors: dict[int, Pose]) -> FrameSample:
    """Every frame looked at and usable (the start sets depend on the poses only)."""
    f = tuple(sorted(priors))
    return FrameSample(f, f, dict.fromkeys(f, 100), f[:: max(len(f) // 24, 1)])


def turn(priors: dict[int, Pose], frames: list[int]) -> float:
    """Largest rotation (deg) of `frames` from the first of them."""
    R0 = priors[frames[0]].R_world_from_cam
    return max(float(np.degrees(np.linalg.norm(so3_log(R0.T @ priors[i].R_world_from_cam)))) for i in frames)


def test_a_drive_that_turns_often_gets_its_longest_stretches_as_start_sets() -> None:
    """Stretches of 4, 9, 2, 3, 8, 6, 9, 7 looked-at frames (none of 10): the three longest, each
    within the turn limit, longest first; a stretch shorter than `min_short_frames` never."""
    lengths = [4, 9, 2, 3, 8, 6, 9, 7]
    priors = turning_drive(lengths)
    o = SampleOptions()
    assert max(lengths) < o.min_start_frames
    sets = start_sets(sample_of(priors), priors, o)
    starts = np.cumsum([0, *lengths])
    stretch = [list(range(a, b)) for a, b in itertools.pairwise(starts)]
    assert sets == [stretch[1], stretch[6], stretch[4]], sets
    assert all(turn(priors, s) <= o.start_turn_deg for s in sets)
    # a drive of nothing but short stretches: no start set
    tiny = turning_drive([3, 4, 2, 4])
    assert start_sets(sample_of(tiny), tiny, o) == []


def test_long_stretches_come_first_in_recording_order() -> None:
    """Two stretches of at least `min_start_frames` (12, 15) and short ones: the long ones in
    recording order, then the longest short one fills the third set."""
    lengths = [6, 12, 3, 15, 8]
    priors = turning_drive(lengths)
    sets = start_sets(sample_of(priors), priors, SampleOptions())
    starts = np.cumsum([0, *lengths])
    stretch = [list(range(a, b)) for a, b in itertools.pairwise(starts)]
    assert sets == [stretch[1], stretch[3], stretch[4]], sets
