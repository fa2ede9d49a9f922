"""Method 3's model-free TIR block: image tracks and the bundle adjustment with the priors, on a
synthetic drive along the bundled Berlin model with the default GNSS/INS errors."""

from __future__ import annotations

import numpy as np
import pytest

from db.citygml.reader import read_model
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.reconstruction.colmap import triangulate
from workers.pipeline.reconstruction.image_tracks import image_tracks
from workers.pipeline.reconstruction.multiview import MultiViewOptions, multiview_block
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.synth import BUNDLED_MODEL, SynthOptions, synthesize
from workers.pipeline.synth.trajectory import DriveOptions

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def drive() -> tuple:
    """16 TIR frames every 2 m past real LoD2 facades; the priors with the true mounting and delay
    (what an accepted calibration gives): the GNSS/INS bias, white noise and vibration remain."""
    _, buildings = read_model(BUNDLED_MODEL)
    opts = SynthOptions(n_frames=16, seed=1, buildings=3, frame_interval_s=0.25,
                        drive=DriveOptions(look_up_deg=10.0))  # fmt: skip
    res = synthesize(buildings, opts)
    tr = res.truth
    priors = prior_poses(res.manifest, None, time_delay_s=tr.time_delay_s, mounting=tr.true_mounting)
    images = [res.frames.load(i) for i in range(opts.n_frames)]
    return res, images, priors


def _relative_errors(poses: list[Pose], truth: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Per consecutive pair: the error of its relative rotation (deg) and of its baseline (m)."""
    rot, base = [], []
    for a in range(len(poses) - 1):
        b = a + 1
        R = poses[b].R_world_from_cam.T @ poses[a].R_world_from_cam
        Rt = truth[b].R_world_from_cam.T @ truth[a].R_world_from_cam
        rot.append(np.degrees(np.arccos(np.clip((np.trace(R.T @ Rt) - 1) / 2, -1, 1))))
        t = poses[b].R_world_from_cam.T @ (poses[a].center - poses[b].center)
        tt = truth[b].R_world_from_cam.T @ (truth[a].center - truth[b].center)
        base.append(np.linalg.norm(t - tt))
    return np.array(rot), np.array(base)


def test_image_tracks_follow_the_scene(drive: tuple) -> None:
    """Tracks from the images alone: triangulated with the true poses, their observations lie
    within a pixel of the point's projection (the rest: repetitive windows, Huber's business)."""
    res, images, priors = drive
    cam, truth = res.manifest.camera, dict(enumerate(res.truth.poses))
    tracks = image_tracks(images.__getitem__, cam, priors)
    assert tracks.n_tracks > 200 and np.all(tracks.lengths() >= 3)
    ids, X = triangulate(cam, tracks, truth, ReconstructionOptions(min_angle_deg=0.5))
    err = []
    for k, t in enumerate(ids):
        for o in np.flatnonzero(tracks.track == t):
            uv, _ = truth[int(tracks.frame[o])].project(cam, X[k : k + 1])
            err.append(np.linalg.norm(uv[0] - tracks.uv[o]))
    assert len(ids) > 0.9 * tracks.n_tracks
    assert np.median(err) < 0.8 and np.mean(np.array(err) < 1.0) > 0.75


def test_multiview_block_makes_the_relative_orientations_consistent(drive: tuple) -> None:
    """The adjusted block's consecutive relative orientations (what the stereo pairs use) are far
    closer to the truth than the priors' (0.2 m / 0.2° of white noise and vibration per frame),
    while the block stays where the GNSS/INS put it (the ICP's business)."""
    res, images, priors = drive
    truth = list(res.truth.poses)
    blk = multiview_block(images.__getitem__, res.manifest.camera, priors)
    assert blk.accepted and len(blk.tied) >= 14 and blk.tie_rms_px < 1.0
    rot0, base0 = _relative_errors(priors, truth)
    rot1, base1 = _relative_errors(list(blk.poses), truth)
    assert np.median(base1) < 0.08 < 0.25 < np.median(base0)
    assert np.median(rot1) < 0.6 * np.median(rot0)
    common0 = np.mean([p.center - t.center for p, t in zip(priors, truth, strict=True)], axis=0)
    common1 = np.mean([p.center - t.center for p, t in zip(blk.poses, truth, strict=True)], axis=0)
    assert np.linalg.norm(common1 - common0) < 0.3


def test_a_block_that_moves_off_its_priors_comes_back_as_the_priors(drive: tuple) -> None:
    """The ties cannot place the block: one whose frames moved on average beyond the limit (here
    0: any move) is refused, and the priors themselves come back."""
    res, images, priors = drive
    opts = MultiViewOptions(max_common_shift_m=0.0)
    blk = multiview_block(images.__getitem__, res.manifest.camera, priors, opts)
    assert not blk.accepted and "moved" in blk.reason and blk.tied == ()
    assert all(p is q for p, q in zip(blk.poses, priors, strict=True))
