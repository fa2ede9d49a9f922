"""The windows of the sequence orientation as independent tasks (`orientation.sequence_windows`,
issue 18 item 3): a synthetic drive with the default error model, its windows run one after the
other, in a forkserver process pool (`workers.pool.pool_map`) and merged in another order, give
the same orientation."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from tests.unit.orientation_scenes import perturb
from workers.pipeline.geometry.manifest import Accuracy, MemoryFrames
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.sequence import (
    SequenceOrientation,
    SequenceOrientationOptions,
    merge_windows,
    orient_sequence,
    orient_window,
    plan_windows,
)
from workers.pipeline.orientation.wireframe import mesh_wireframe
from workers.pool import pool_map

N = 24
ACC = Accuracy(position_m=np.array([0.5, 0.5, 0.5]), attitude_deg=np.array([0.5, 0.5, 0.5]))
# windows (0, 16), (8, 24): frames 8-15 are in both
OPTIONS = SequenceOrientationOptions(window_frames=16, overlap_frames=8)


@pytest.fixture(scope="module")
def drive():
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    opts = SynthOptions(platform="drive", n_frames=N, seed=1, buildings=2)
    res = synthesize(procedural_block(6, seed=1), opts)
    frames = MemoryFrames({i: res.frames.load(i) for i in range(N)})
    rng = np.random.default_rng(5)
    common_m, common_deg = np.array([0.4, -0.3, 0.3]), np.array([0.3, -0.4, 0.2])
    prior = {i: perturb(T, common_m + rng.normal(0, 0.2, 3), common_deg + rng.normal(0, 0.15, 3))
             for i, T in enumerate(res.truth.poses)}  # fmt: skip
    times = {i: f.time for i, f in enumerate(res.manifest.frames)}
    args = (res.manifest.camera, RayCaster(res.mesh), list(range(N)), frames, prior, times, ACC, OPTIONS)
    return res, args


@pytest.fixture(scope="module")
def serial(drive) -> SequenceOrientation:
    return orient_sequence(*drive[1])


def _assert_same(a: SequenceOrientation, b: SequenceOrientation, atol: float = 1e-9) -> None:
    assert a.poses.keys() == b.poses.keys() and a.oriented == b.oriented
    for f in a.poses:
        pa, pb = a.poses[f], b.poses[f]
        np.testing.assert_allclose(pa.R_world_from_cam, pb.R_world_from_cam, rtol=0, atol=atol)
        np.testing.assert_allclose(pa.center, pb.center, rtol=0, atol=atol)
    for f in a.covariance:
        np.testing.assert_allclose(a.covariance[f], b.covariance[f], rtol=1e-7, atol=1e-15)
    assert a.blocks == b.blocks and a.ties == b.ties
    rms = [[so.tie_rms_px[f] for f in so.oriented] for so in (a, b)]
    np.testing.assert_allclose(rms[0], rms[1], rtol=0, atol=atol)
    np.testing.assert_array_equal(a.tracks.frame, b.tracks.frame)
    np.testing.assert_array_equal(a.tracks.track, b.tracks.track)
    np.testing.assert_allclose(a.tracks.uv, b.tracks.uv, rtol=0, atol=atol)
    np.testing.assert_allclose(a.tracks.point, b.tracks.point, rtol=0, atol=atol)


def test_the_windows_overlap_and_the_serial_run_orients_the_drive(serial) -> None:
    assert [b["frames"] for b in serial.blocks] == [[0, 15], [8, 23]]
    assert all(b["accepted"] for b in serial.blocks), serial.blocks
    assert serial.oriented == list(range(N))
    # each frame's ties come from one window only: the one that gave it its pose
    assert set(np.unique(serial.tracks.frame).tolist()) <= set(serial.oriented)


def test_windows_in_a_process_pool_give_the_serial_result(drive, serial) -> None:
    pooled = orient_sequence(*drive[1], map_windows=pool_map(2))
    _assert_same(serial, pooled)


def test_windows_merge_in_any_order_and_every_window_is_needed(drive, serial) -> None:
    plan = plan_windows(*drive[1])
    # a task travels without its ray caster and rebuilds it from the mesh; with the planner's
    # scene wireframe, which equals the one made from the mesh
    task = pickle.loads(pickle.dumps(plan.tasks[1]))
    assert task.caster is None and task.frames == tuple(range(8, 24))
    made = mesh_wireframe(task.mesh, task.options.coregister.edges)
    assert task.wireframe is not None and task.wireframe is not plan.tasks[1].wireframe
    assert np.array_equal(task.wireframe.vertices, made.vertices)
    assert np.array_equal(task.wireframe.edges, made.edges)
    results = [orient_window(task), orient_window(plan.tasks[0])]
    _assert_same(serial, merge_windows(plan, results))
    with pytest.raises(ValueError, match=r"windows \[0\]"):
        merge_windows(plan, results[:1])


def test_a_scene_without_buildings_plans_no_windows(drive) -> None:
    from workers.pipeline.geometry.raycast import build_scene_mesh

    camera, _, frames, source, prior, times, acc, opts = drive[1]
    plan = plan_windows(camera, RayCaster(build_scene_mesh([])), frames, source, prior, times, acc, opts)
    assert plan.tasks == ()
    so = orient_sequence(camera, RayCaster(build_scene_mesh([])), frames, source, prior, times, acc, opts)
    assert so.oriented == [] and so.poses == prior
