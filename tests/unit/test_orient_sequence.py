"""Sequence orientation (`workers.pipeline.orient_sequence`): a synthetic drive with the default
error model, oriented in blocks from priors with a common and a per-frame error, against the true
poses (reprojection of the cluster buildings' edges)."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import workers.pipeline.orient_sequence as orient_module
from tests.unit.orientation_scenes import ArraySource, perturb, reprojection_rms
from workers.pipeline.coregister import CoregisterOptions, refine_building
from workers.pipeline.orient_sequence import SequenceOrientationOptions, orient_sequence, windows
from workers.pipeline.raycast import RayCaster
from workers.pipeline.sequence import Accuracy

N = 24
ACC = Accuracy(position_m=np.array([0.5, 0.5, 0.5]), attitude_deg=np.array([0.5, 0.5, 0.5]))


@pytest.fixture(scope="module")
def drive():
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    res = synthesize(procedural_block(6, seed=1),
                     SynthOptions(platform="drive", n_frames=N, seed=1, buildings=2))
    images = {i: res.frames.load(i) for i in range(N)}
    rng = np.random.default_rng(5)
    # what a sequence calibration leaves: a common error, and each frame's white noise and vibration
    common_m, common_deg = np.array([0.4, -0.3, 0.3]), np.array([0.3, -0.4, 0.2])
    prior = {i: perturb(T, common_m + rng.normal(0, 0.2, 3), common_deg + rng.normal(0, 0.15, 3))
             for i, T in enumerate(res.truth.poses)}
    times = {i: f.time for i, f in enumerate(res.manifest.frames)}
    return res, images, prior, times, RayCaster(res.mesh)


def _pairs(res, poses) -> np.ndarray:
    """Reprojection RMS (px) of every (frame, cluster building) pair the true pose sees."""
    cam, T = res.manifest.camera, res.truth.poses
    out = []
    for b in res.buildings:
        if b.id not in res.truth.cluster:
            continue
        for i in range(N):
            if np.isfinite(reprojection_rms(cam, b, T[i], T[i])):
                out.append(reprojection_rms(cam, b, poses[i], T[i]))
    return np.array(out)


def test_doctests_and_windows() -> None:
    assert doctest.testmod(orient_module).failed == 0
    o = SequenceOrientationOptions(window_frames=10, overlap_frames=4)
    t = [0.1 * k for k in range(25)]
    w = windows(t, o)
    assert w[0] == (0, 10) and w[-1] == (15, 25)
    assert all(b - a == 10 for a, b in w) and all(w[k + 1][0] < w[k][1] for k in range(len(w) - 1))
    # a gap splits; a short run is one window
    w2 = windows([0.0, 0.1, 0.2, 9.0, 9.1], o)
    assert w2 == [(0, 3), (3, 5)]
    assert windows([], o) == []


@pytest.mark.parametrize("window, overlap", [(120, 30), (16, 8)])
def test_drive_is_oriented_below_a_pixel(drive, window: int, overlap: int) -> None:
    # one block of all frames, and three overlapping blocks (frames take the pose of the block
    # where they lie furthest from the ends)
    res, images, prior, times, caster = drive
    before = _pairs(res, prior)
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), ArraySource(images), prior, times, ACC,
                         SequenceOrientationOptions(window_frames=window, overlap_frames=overlap))
    assert len(so.blocks) == (1 if window >= N else 2)
    after = _pairs(res, so.poses)
    assert np.median(before) > 10.0
    assert all(b["accepted"] for b in so.blocks), so.blocks
    assert so.oriented == list(range(N))
    assert np.mean(after < 1.0) >= 0.95 and np.median(after) < 0.5 and after.max() < 1.5
    assert so.tracks.n_tracks > 100
    doc = so.to_dict()
    assert doc["frames"] == N and doc["frames_oriented"] == N and len(doc["blocks"]) == len(so.blocks)


def test_units_refine_from_the_sequence_orientation(drive) -> None:
    res, images, prior, times, caster = drive
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), ArraySource(images), prior, times, ACC)
    cam, T = res.manifest.camera, res.truth.poses
    for b in res.buildings:
        if b.id not in res.truth.cluster:
            continue
        seen = [i for i in range(N) if np.isfinite(reprojection_rms(cam, b, T[i], T[i]))]
        if len(seen) < 2:
            continue
        part = so.for_frames(seen)
        assert set(part.poses) == set(seen) and set(np.unique(part.tracks.frame)) <= set(seen)
        assert part.tracks.lengths().min() >= 2
        out = refine_building(cam, b, caster, seen, ArraySource(images), {i: prior[i] for i in seen}, ACC,
                              CoregisterOptions(), times, part)
        after = np.array([reprojection_rms(cam, b, out[i].pose, T[i]) for i in seen])
        refined = np.array([out[i].status == "refined" for i in seen])
        assert refined.mean() >= 0.9
        assert np.all(after[refined] < 1.0)
        assert all(out[i].pose is prior[i] for i in seen if out[i].status == "prior")


def test_frames_without_the_model_keep_their_priors(drive) -> None:
    res, _, prior, times, caster = drive
    rng = np.random.default_rng(1)
    shape = (res.manifest.camera.height, res.manifest.camera.width)
    blank = {i: (280.0 + rng.normal(0, 0.05, shape)).astype(np.float32) for i in range(N)}
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), ArraySource(blank), prior, times, ACC)
    assert not any(b["accepted"] for b in so.blocks)
    assert so.oriented == [] and all(so.poses[i] is prior[i] for i in range(N))
    assert so.tracks.n_tracks == 0
