"""The orient stage's RGB step (`RunOptions.rgb`, `workers.orient_rgb`): a synthetic drive past
the bundled Berlin model with its RGB camera, the GNSS/INS errors on, run through the shipped
stages (ingest, calibrate, orient with `rgb=True`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from workers import job
from workers.job import RunOptions
from workers.orient_rgb import rgb_registered
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, RgbOptions, SynthOptions, synthesize

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory):  # -> (SynthResult, package with rgb/, without)
    folder = tmp_path_factory.mktemp("rgbdrive")
    _, buildings = read_model(BUNDLED_MODEL)
    opts = SynthOptions(
        n_frames=16, seed=1, buildings=2, frame_interval_s=0.25, errors=ErrorOptions(),
        rgb=RgbOptions(width=640, height=512), model_path=str(BUNDLED_MODEL),
    )  # fmt: skip
    res = synthesize(buildings, opts)
    with_rgb = write_synthetic_package(res, folder / "with")
    without = write_synthetic_package(synthesize(buildings, replace(opts, rgb=None)), folder / "without")
    return res, with_rgb, without


def test_without_an_rgb_camera_the_poses_stay(drive) -> None:
    _, _, without = drive
    ing = job.ingest(BUNDLED_MODEL, without, RunOptions.build(rgb=True))
    poses, fig = rgb_registered(ing, ing.priors)
    assert fig == {"accepted": False, "reason": "the sequence has no rgb_camera"}
    assert all(p is q for p, q in zip(poses, ing.priors, strict=True))


def test_orient_stage_registers_on_the_rgb_block_and_reports_it(drive, monkeypatch) -> None:
    """The orient stage with `rgb=True` runs the registration from the calibrated priors (the
    real `rgb_registered`, observed on its way through), reports its figures, and the sequence
    orientation starts from the poses it hands on: the input, adjusted by the multi-view block
    (within the priors' per-frame noise) when it was accepted, moved by the reported rigid
    transform (the input itself when refused)."""
    _, with_rgb, _ = drive
    options = RunOptions.build(rgb=True)
    ing = job.ingest(BUNDLED_MODEL, with_rgb, options)
    calibrated = job.calibrate(ing, options)
    seen: list = []

    def observed(ingested, poses):  # the shipped step, its input and output recorded
        out = rgb_registered(ingested, poses)
        seen.append((list(poses), out))
        return out

    monkeypatch.setattr(job, "rgb_registered", observed)
    oriented = job.orient(ing, calibrated, options)
    assert oriented.report["run"] is True, oriented.report
    assert len(seen) == 1
    given, (start, fig) = seen[0]
    assert all(p is q for p, q in zip(given, calibrated.priors, strict=True))
    assert {"accepted", "reason", "points_tir", "points_rgb", "transform"} <= set(fig), fig
    assert oriented.report["rgb"] == fig
    T = np.asarray(fig["transform"])
    block = fig.get("multiview", {}).get("accepted", False) and fig["accepted"]
    for p, q in zip(start, calibrated.priors, strict=True):
        R_back = T[:3, :3].T @ p.R_world_from_cam  # `p` moved back by the rigid transform
        C_back = T[:3, :3].T @ (p.center - T[:3, 3])
        if block:  # the multi-view block moved each frame within its prior's per-frame noise
            turn = np.degrees(np.arccos(np.clip((np.trace(R_back.T @ q.R_world_from_cam) - 1) / 2, -1, 1)))
            assert turn < 1.0 and np.linalg.norm(C_back - q.center) < 1.0
        else:
            assert np.allclose(R_back, q.R_world_from_cam, atol=1e-9)
        if not fig["accepted"]:
            assert np.allclose(p.center, q.center) and np.allclose(p.R_world_from_cam, q.R_world_from_cam)
