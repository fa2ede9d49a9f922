"""Packages written by synth read back through the sequence reader; truth files round-trip."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from typer.testing import CliRunner

from db.sequence_package import open_package
from db.synth_files import load_buildings, load_truth, write_synthetic_package
from services.cli import app
from workers.pipeline.synth import (
    SynthError,
    SynthOptions,
    procedural_block,
    synthesize,
    thermal_scene_for_truth,
)
from workers.pipeline.synth.render import default_camera

SMALL = default_camera(96, 80)


@pytest.fixture(scope="module")
def result():
    blds = procedural_block(6, seed=3)
    return synthesize(
        blds, SynthOptions(n_frames=15, seed=3, buildings=2, camera=SMALL, n_gcps=6, procedural=(6, 3))
    )


def test_written_package_reads_back(result, tmp_path):
    out = write_synthetic_package(result, tmp_path / "pkg", tmp_path / "truth.json")
    with open_package(out) as pkg:
        m = pkg.manifest
        assert len(m.frames) == 15 and m.camera == SMALL and m.platform == "drive"
        assert m.imu is not None and len(m.imu.time) > 100
        assert m.gcps is not None and len(m.gcps.points) > 0
        for i in (0, 14):
            assert np.array_equal(pkg.frames.load(i), result.frames.load(i))
            assert np.allclose(m.frames[i].position, result.manifest.frames[i].position)
    assert not (out / "truth.json").exists()
    truth = load_truth(tmp_path / "truth.json")
    assert truth.package == "pkg"
    for a, b in zip(truth.poses, result.truth.poses, strict=True):
        assert np.allclose(a.R_world_from_cam, b.R_world_from_cam, atol=1e-12)
        assert np.allclose(a.center, b.center, atol=1e-9)
    assert truth.time_delay_s == result.truth.time_delay_s
    assert [x.id for x in truth.anomalies] == [x.id for x in result.truth.anomalies]
    assert truth.thermal == result.truth.thermal and truth.sensor == result.truth.sensor


def test_truth_rebuilds_scene_and_field(result, tmp_path):
    write_synthetic_package(result, tmp_path / "p", tmp_path / "t.json")
    truth = load_truth(tmp_path / "t.json")
    blds = load_buildings(truth)
    assert [b.id for b in blds] == list(truth.buildings)
    th = thermal_scene_for_truth(truth, blds[:2])
    pid = blds[1].polygons[2].id
    X = np.array([[*(blds[1].bounds()[0][:2] + 1.0), blds[1].bounds()[0][2] + 2.0]])
    assert np.allclose(th.surface_temperature(pid, X), result.thermal.surface_temperature(pid, X), atol=1e-3)


def test_frames_are_picklable_and_deterministic(result):
    frames = pickle.loads(pickle.dumps(result.frames))
    assert np.array_equal(frames[2], result.frames[2])
    assert frames[2].dtype == np.uint16 and frames[2].shape == (80, 96)
    assert len(frames) == 15


def test_manifest_crs_from_the_model_srs_name():
    adv = procedural_block(2, seed=1, srs_name="urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH")
    res = synthesize(adv, SynthOptions(n_frames=1, buildings=1, camera=default_camera(32, 24)))
    assert res.manifest.crs == "EPSG:25832"
    local = procedural_block(2, seed=1, srs_name="my-local-grid")
    res = synthesize(local, SynthOptions(n_frames=1, buildings=1, camera=default_camera(32, 24)))
    assert res.manifest.crs == "model"


def test_truth_file_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "something/1"}))
    with pytest.raises(SynthError, match="format"):
        load_truth(bad)
    with pytest.raises(SynthError, match="cannot read"):
        load_truth(tmp_path / "missing.json")


def test_cli_writes_a_readable_package(tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli" / "pkg"
    r = runner.invoke(
        app,
        ["synth", "--procedural", "5", "--platform", "flight", "--frames", "3", "--seed", "2",
         "--width", "64", "--image-height", "48", "--no-errors", "-o", str(out)],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    truth = load_truth(tmp_path / "cli" / "pkg.truth.json")
    assert truth.platform == "flight" and truth.time_delay_s == 0.0
    with open_package(out) as pkg:
        assert len(pkg.manifest.frames) == 3
        assert np.isfinite(pkg.frames.load(2)).all()
    r = runner.invoke(app, ["synth", "--procedural", "3", "--buildings", "nope", "-o", str(tmp_path / "x")])
    assert r.exit_code == 1 and "unknown building" in r.output


def test_cli_terrestrial_walk_with_planted_leaks(tmp_path):
    """`--platform terrestrial` walks a hand-held camera along one facade; `--leaks` sets the
    planted leaks per building (their truth with half-maximum outlines in the truth file)."""
    runner = CliRunner()
    out = tmp_path / "walk"
    r = runner.invoke(
        app,
        ["synth", "--procedural", "3", "--platform", "terrestrial", "--buildings", "1", "--frames", "3",
         "--leaks", "4", "--width", "64", "--image-height", "48", "--no-errors", "-o", str(out)],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    truth = load_truth(tmp_path / "walk.truth.json")
    assert truth.platform == "terrestrial"
    assert len(truth.anomalies) >= 4  # Poisson mean 4 per rendered building
    r = runner.invoke(app, ["synth", "--procedural", "3", "--platform", "boat", "-o", str(tmp_path / "b")])
    assert r.exit_code != 0 and "terrestrial" in r.output
