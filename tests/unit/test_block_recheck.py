"""The recheck of an adjusted block (`workers.pipeline.orientation.block_recheck`): frames tied to
the block by one wrong short track, whose own model edges contradict the poses the track bends
them to, on a synthetic drive past a procedural block (rendered frames, the tracker's tracks)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.unit.orientation_scenes import perturb, reprojection_rms
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block import BlockOptions, adjust_block
from workers.pipeline.orientation.block_recheck import (
    RecheckOptions,
    recheck_block,
    restart_poses,
    suspect_frames,
)
from workers.pipeline.orientation.bundle import bundle_adjust
from workers.pipeline.orientation.edge_observations import FrameWireframes
from workers.pipeline.orientation.priors import frame_noise_covariance
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.orientation.wireframe import mesh_wireframe

N = 24
#: the frames the wrong track ties (their own ties removed: weakly tied, as frames 4-6 of the NRW
#: errors drive, one tie each) and the rotations about the camera's x axis (degrees) its
#: observations were made with
BENT = (2, 3, 4)
BEND_DEG = (-0.5, 0.0, 0.8)
COMMON = np.diag([np.radians(2.0) ** -2] * 3 + [1.0] * 3)


@pytest.fixture(scope="module")
def scene():
    """The drive, its images, priors with a common error and white noise, the ray caster, the
    scene wireframe per frame, the tracker's tracks with the frames `BENT` tied only by a wrong
    track, and the bundle adjustment that fits it (the old behaviour)."""
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    res = synthesize(
        procedural_block(6, seed=1), SynthOptions(platform="drive", n_frames=N, seed=1, buildings=2)
    )
    images = {i: res.frames.load(i) for i in range(N)}
    rng = np.random.default_rng(5)
    common_m, common_deg = np.array([0.4, -0.3, 0.3]), np.array([0.3, -0.4, 0.2])
    prior = {
        i: perturb(T, common_m + rng.normal(0, 0.2, 3), common_deg + rng.normal(0, 0.15, 3))
        for i, T in enumerate(res.truth.poses)
    }
    caster = RayCaster(res.mesh)
    cam, truth, frames = res.manifest.camera, res.truth.poses, list(range(N))
    wf = mesh_wireframe(caster.mesh)
    off = BlockOptions(recheck=RecheckOptions(enabled=False))
    _, tracks, _ = adjust_block(cam, wf, caster, frames, images, prior, prior, COMMON, off)
    # the wrong track: a facade point seen in the middle of frame BENT[0], observed in the three
    # frames as poses turned by BEND_DEG would see it (a mismatch along the drive)
    k = BENT[0]
    d = truth[k].R_world_from_cam @ cam.bearing(np.array([[cam.cx, cam.cy + 60.0]]))[0]
    d /= np.linalg.norm(d)
    hit = caster.cast(truth[k].center[None], d[None])
    X = truth[k].center + hit.t[0] * d
    uv = [perturb(truth[f], np.zeros(3), np.array([b, 0.0, 0.0])).project(cam, X[None])[0][0]
          for f, b in zip(BENT, BEND_DEG, strict=True)]  # fmt: skip
    wrong = Tracks(np.zeros(3, int), np.array(BENT), np.array(uv), X[None], hit.normal[:1])
    tracks = Tracks.concat([tracks.subset(~np.isin(tracks.frame, BENT)), wrong])
    white = np.linalg.inv(frame_noise_covariance(0.3, 0.3))
    fw = FrameWireframes(wf, cam)

    def readjust(start, tr):
        return bundle_adjust(
            cam, frames, images, start, prior, dict.fromkeys(frames, white), COMMON, tr, fw, caster
        )

    return res, prior, tracks, readjust, readjust(prior, tracks)


def _error_px(res, poses, f: int) -> float:
    """Median over the buildings frame `f` sees of their edges' reprojection RMS (px), `poses[f]`
    against the truth."""
    cam, T = res.manifest.camera, res.truth.poses
    v = [reprojection_rms(cam, b, poses[f], T[f]) for b in res.buildings]
    return float(np.median([x for x in v if np.isfinite(x)]))


def test_a_wrong_short_track_bends_weakly_tied_frames_off_their_edges(scene) -> None:
    """The old behaviour: the bundle bends the frames to the wrong track; their edges fit worse
    than the block's, which is what the recheck reads."""
    res, _, _, _, bent = scene
    err = {f: _error_px(res, bent.poses, f) for f in range(N)}
    assert max(err[f] for f in BENT) > 5.0, err
    assert np.median([err[f] for f in range(N) if f not in BENT]) < 0.5
    assert all(bent.ties[f] < 8 for f in BENT)
    found = suspect_frames(list(range(N)), bent)
    assert {BENT[0], BENT[2]} <= set(found) and set(found) <= set(BENT), found


def test_the_recheck_drops_the_wrong_ties_and_brings_the_frames_back(scene) -> None:
    res, prior, tracks, readjust, bent = scene
    frames = list(range(N))
    out, kept, rechecked = recheck_block(frames, prior, bent, tracks, readjust)
    assert rechecked and set(rechecked) <= set(BENT)
    err = {f: _error_px(res, out.poses, f) for f in frames}
    assert max(err[f] for f in BENT) < 1.0, err
    # the other frames stay where they were (their ties are kept)
    others = [f for f in frames if f not in BENT]
    assert max(abs(err[f] - _error_px(res, bent.poses, f)) for f in others) < 0.1
    assert len(kept.frame) == int(np.sum(~np.isin(tracks.frame, rechecked)))
    assert len(out.inlier) == len(kept.frame)


def test_the_recheck_keeps_a_block_it_cannot_improve(scene) -> None:
    """A second adjustment that does not fit the suspects' edges better is not taken; none runs
    without suspects or when the recheck is off."""
    _, prior, tracks, _, bent = scene
    frames = list(range(N))
    calls = []

    def worse(start, tr):
        calls.append(1)
        return bent  # "adjusted again": the same edge figures, no gain

    out, kept, rechecked = recheck_block(frames, prior, bent, tracks, worse)
    assert calls and out is bent and kept is tracks and rechecked == []
    calls.clear()
    never = RecheckOptions(rms_ratio=1e9)
    assert recheck_block(frames, prior, bent, tracks, worse, never)[2] == [] and not calls
    assert recheck_block(frames, prior, bent, tracks, worse, RecheckOptions(enabled=False))[0] is bent
    assert not calls
    # taken when a suspect's edges fit clearly better and none's fit worse; not when one's rise
    found = suspect_frames(frames, bent)
    rms = dict(bent.edge_rms_px)
    halved = replace(bent, edge_rms_px={**rms, found[0]: 0.5 * rms[found[0]]})
    assert recheck_block(frames, prior, bent, tracks, lambda s, t: halved)[0] is halved
    mixed = replace(halved, edge_rms_px={**halved.edge_rms_px, found[-1]: 1.5 * rms[found[-1]]})
    assert recheck_block(frames, prior, bent, tracks, lambda s, t: mixed)[0] is bent


def test_restart_poses_interpolate_the_neighbours_correction(scene) -> None:
    _, prior, _, _, bent = scene
    frames = list(range(N))
    start = restart_poses(frames, prior, bent.poses, [5])
    assert all(start[f] is bent.poses[f] for f in frames if f != 5)
    from workers.pipeline.geometry.pose_increments import pose_delta

    want = 0.5 * (pose_delta(prior[4], bent.poses[4]) + pose_delta(prior[6], bent.poses[6]))
    np.testing.assert_allclose(pose_delta(prior[5], start[5]), want, atol=1e-9)
    # every frame a suspect: nothing to interpolate from, the poses stay
    assert restart_poses(frames, prior, bent.poses, frames) == {f: bent.poses[f] for f in frames}
