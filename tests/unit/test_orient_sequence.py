"""Sequence orientation (`workers.pipeline.orientation.sequence`): a synthetic drive with the default
error model, oriented in blocks from priors with a common and a per-frame error, against the true
poses (reprojection of the cluster buildings' edges)."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import workers.pipeline.orientation.sequence as orient_module
from tests.unit.orientation_scenes import perturb, reprojection_rms
from workers.pipeline.geometry.manifest import Accuracy, MemoryFrames
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block import BlockOptions, UnitSequence, anchoring, refine_from_sequence
from workers.pipeline.orientation.building import CoregisterOptions, refine_building
from workers.pipeline.orientation.sequence import SequenceOrientationOptions, orient_sequence, windows
from workers.pipeline.orientation.wireframe import building_wireframe

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
    # one block of all frames, and two overlapping blocks (frames take the pose of the block
    # where they lie furthest from the ends)
    res, images, prior, times, caster = drive
    before = _pairs(res, prior)
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), MemoryFrames(images), prior, times, ACC,
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


@pytest.fixture(scope="module")
def oriented(drive):
    res, images, prior, times, caster = drive
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), MemoryFrames(images), prior, times, ACC,
                         SequenceOrientationOptions(window_frames=16, overlap_frames=8))
    return so


def _cluster_frames(res) -> list[tuple[object, list[int]]]:
    cam, T = res.manifest.camera, res.truth.poses
    out = []
    for b in res.buildings:
        if b.id in res.truth.cluster:
            seen = [i for i in range(N) if np.isfinite(reprojection_rms(cam, b, T[i], T[i]))]
            if len(seen) >= 4:
                out.append((b, seen))
    return out


def test_units_take_the_sequence_poses_where_the_buildings_edges_confirm_them(drive, oriented) -> None:
    res, images, prior, _, caster = drive
    cam, T = res.manifest.camera, res.truth.poses
    units = _cluster_frames(res)
    assert len(units) >= 1
    for b, seen in units:
        part = oriented.for_frames(seen)
        assert set(part.poses) == set(seen) and all(part.ties[i] > 0 for i in seen)
        out, reason = refine_from_sequence(cam, building_wireframe(b), caster, seen, images, prior, part)
        assert reason == ""
        refined = [i for i in seen if out[i].status == "refined"]
        assert len(refined) >= 0.9 * len(seen)
        assert all(out[i].pose is part.poses[i] for i in refined)
        assert all(reprojection_rms(cam, b, out[i].pose, T[i]) < 1.0 for i in refined)
        assert all(out[i].pose is prior[i] for i in seen if out[i].status == "prior")
        assert all(out[i].matches > 0 and np.isfinite(out[i].rms_px) for i in refined)


def test_units_reject_what_the_sequence_leaves_open_or_the_building_contradicts(drive, oriented) -> None:
    res, images, prior, times, caster = drive
    cam = res.manifest.camera
    b, seen = _cluster_frames(res)[0]
    part = oriented.for_frames(seen)
    # the same poses with a hundred times their covariance: not determined, priors kept
    inflated = {i: 1e4 * c for i, c in part.covariance.items()}
    loose = UnitSequence(part.poses, inflated, part.ties, part.tie_rms_px)
    out, reason = refine_from_sequence(cam, building_wireframe(b), caster, seen, images, prior, loose)
    assert reason == "" and all(out[i].status == "prior" for i in seen)
    # poses 1 m beside the truth, claimed to the centimetre: the building's edges reject them
    # everywhere, and refine_building orients the building from its priors instead
    off = {i: Pose(p.R_world_from_cam, p.center + np.array([1.0, 1.0, 0.0])) for i, p in part.poses.items()}
    wrong = UnitSequence(off, part.covariance, part.ties, part.tie_rms_px)
    out, reason = refine_from_sequence(cam, building_wireframe(b), caster, seen, images, prior, wrong)
    assert reason and all(out[i].status == "prior" for i in seen)
    got = refine_building(cam, b, caster, seen, MemoryFrames(images), {i: prior[i] for i in seen}, ACC,
                          CoregisterOptions(), times, wrong)
    assert not any(got[i].pose is off[i] for i in seen)


def test_a_unit_confirms_by_support_above_null_with_its_own_lower_floor() -> None:
    """The sequence acceptance looks for the model (mean support >= `min_mean_support`); a unit
    only checks that its building's edges do not contradict the poses: support clearly above the
    null support, with the lower floor `confirm_min_mean_support`."""
    o = BlockOptions(anchor_frames=2, min_mean_support=0.3, min_support_gain=0.15,
                     confirm_min_mean_support=0.1)
    frames = list(range(6))
    # a building leaving the view: support 0.25 against a null support of 0.01
    leaving = dict.fromkeys(frames, 0.25), dict.fromkeys(frames, 0.01)
    assert not any(anchoring(frames, *leaving, o).values())
    assert all(anchoring(frames, *leaving, o, o.confirm_min_mean_support).values())
    # clutter: as much support off the edges as on them contradicts the poses at either floor
    clutter = dict.fromkeys(frames, 0.5), dict.fromkeys(frames, 0.42)
    assert not any(anchoring(frames, *clutter, o, o.confirm_min_mean_support).values())
    # below the floor, whatever the null support
    faint = dict.fromkeys(frames, 0.08), dict.fromkeys(frames, -0.1)
    assert not any(anchoring(frames, *faint, o, o.confirm_min_mean_support).values())
    # no frame sees the building's edges: undecided
    assert set(anchoring(frames, {}, {}, o, o.confirm_min_mean_support).values()) == {None}


def test_each_frame_keeps_the_ties_of_the_window_that_oriented_it(oriented) -> None:
    tr = oriented.tracks
    assert tr.n_tracks > 50 and tr.lengths().min() >= 2
    # overlapping windows track the same points again: no frame may hold the same point twice
    for f in np.unique(tr.frame):
        uv = np.round(tr.uv[tr.frame == f], 2)
        assert len(np.unique(uv, axis=0)) == len(uv), f
    assert set(oriented.ties) == set(oriented.covariance) and all(v > 0 for v in oriented.ties.values())


def test_window_options_are_checked() -> None:
    with pytest.raises(ValueError, match="overlap"):
        SequenceOrientationOptions(window_frames=10, overlap_frames=10)


def test_frames_without_the_model_keep_their_priors(drive) -> None:
    res, _, prior, times, caster = drive
    rng = np.random.default_rng(1)
    shape = (res.manifest.camera.height, res.manifest.camera.width)
    blank = {i: (280.0 + rng.normal(0, 0.05, shape)).astype(np.float32) for i in range(N)}
    so = orient_sequence(res.manifest.camera, caster, list(range(N)), MemoryFrames(blank), prior, times, ACC)
    assert not any(b["accepted"] for b in so.blocks)
    assert so.oriented == [] and all(so.poses[i] is prior[i] for i in range(N))
    assert so.tracks.n_tracks == 0


def test_the_bundle_fits_the_model_edges_without_ties(drive) -> None:
    """The edge observations of `bundle_adjust` alone (no tie points), on the drive's frames from
    priors with a common error: the common error goes, the edges end on their image edges."""
    from workers.pipeline.orientation.bundle import bundle_adjust
    from workers.pipeline.orientation.priors import frame_noise_covariance
    from workers.pipeline.orientation.tracks import Tracks
    from workers.pipeline.orientation.wireframe import mesh_wireframe

    res, images, prior, _, caster = drive
    frames = list(range(N))
    white = np.linalg.inv(frame_noise_covariance(0.3, 0.3))
    common = np.diag([np.radians(2.0) ** -2] * 3 + [1.0] * 3)
    out = bundle_adjust(res.manifest.camera, frames, images, prior, prior, dict.fromkeys(frames, white),
                        common, Tracks.empty(), mesh_wireframe(caster.mesh), caster)
    before, after = _pairs(res, prior), _pairs(res, out.poses)
    assert out.converged and len(out.edge_support) > N // 2
    assert np.mean(list(out.edge_support.values())) > 0.7
    assert np.median(after) < 0.3 * np.median(before)


def test_the_stacked_edge_equations_are_the_frame_by_frame_ones(drive) -> None:
    """`bundle_edges.stacked_edge_equations` (all frames at once, the bundle's edge term) gives
    each frame's `edge_observations.normal_equations` (no corners, no prior) to rounding, at the
    start radius and at the final one."""
    from dataclasses import replace

    from workers.pipeline.orientation.bundle_edges import stacked_edge_equations
    from workers.pipeline.orientation.edge_observations import FrameWireframes, frame_edges, normal_equations
    from workers.pipeline.orientation.features import FeatureOptions
    from workers.pipeline.orientation.fit_options import FrameFitOptions
    from workers.pipeline.orientation.wireframe import EdgeOptions, mesh_wireframe

    res, images, prior, _, caster = drive
    cam, fo = res.manifest.camera, FrameFitOptions()
    wf = FrameWireframes(mesh_wireframe(caster.mesh), cam)
    edges = frame_edges(cam, wf, caster, list(range(N)), images, prior, 40.0, fo, EdgeOptions(),
                        FeatureOptions())
    used = [f for f, ed in edges.items() if len(ed.vis.points) >= fo.min_samples]
    assert len(used) > N // 2
    for R_e in (16.0, 3.0):
        fo_it = replace(fo, tukey_min_px=max(fo.tukey_min_px, R_e / 3))
        H, g = stacked_edge_equations(cam, [prior[f] for f in used], [edges[f].vis for f in used],
                                      [edges[f].feats for f in used], R_e, fo_it)
        for k, f in enumerate(used):
            He, ge, *_ = normal_equations(cam, prior[f], edges[f].vis, edges[f].feats, np.zeros((0, 2)), R_e,
                                          fo.point_radius_min_px, prior[f], np.zeros((6, 6)), fo_it)
            np.testing.assert_allclose(H[k], He, rtol=1e-6, atol=1e-9 * np.abs(He).max())
            np.testing.assert_allclose(g[k], ge, rtol=1e-6, atol=1e-9 * np.abs(ge).max() + 1e-12)
