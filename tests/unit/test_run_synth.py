"""`citytherm run` on a synthetic drive around real buildings with error-free poses: texture
RMSE, misregistration and coverage against the generator's ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.synth_files import write_synthetic_package
from workers.job import RunOptions
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.run import run_job
from workers.synth_eval import texture_accuracy


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthdrive")
    _, buildings = read_model(BUNDLED_MODEL)
    res = synthesize(
        buildings,
        SynthOptions(
            n_frames=20,
            seed=3,
            buildings=2,
            frame_interval_s=0.2,
            errors=ErrorOptions(enabled=False),
            model_path=str(BUNDLED_MODEL),
        ),
    )
    pkg = write_synthetic_package(res, folder / "seq")
    out = folder / "out"
    summary = run_job(
        BUNDLED_MODEL, pkg, out, RunOptions.build(resolution_px_per_m=10, refine=False, display=False)
    )
    return res, out, summary


@pytest.mark.slow
def test_error_free_drive_meets_the_texture_bars_with_margin(drive):
    res, out, summary = drive
    acc = texture_accuracy(out, res)
    assert acc["texels_observed"] > 50000, acc
    assert acc["rmse_k"] < 0.3, acc  # bar 0.35 K
    assert acc["misregistration_median_texel"] < 0.2, acc  # bar 0.3 texel
    # coverage counts every texel some frame sees point-wise, grazing ones (up to the 80° limit)
    # included; the clean-pixel test rightly rejects grazing texels whose sampling footprint
    # reaches past their polygon, so this self-made figure stays below 1. The measure against an
    # independent texturer is tests/unit/test_texture_vs_reference.py.
    assert acc["coverage"] > 0.85, acc
    assert {r.building_id for r in summary.results} & set(res.truth.cluster)


@pytest.mark.slow
def test_output_of_a_real_model_validates_and_keeps_its_ids(drive):
    _, out, summary = drive
    assert validate_citygml2(out / "textured.gml") == []
    _, back = read_model(out / "textured.gml")
    _, src = read_model(BUNDLED_MODEL)
    src_by_id = {b.id: b for b in src}
    assert back and {b.id for b in back} <= {r.building_id for r in summary.results}
    for b in back:
        assert [p.id for p in b.iter_polygons()] == [p.id for p in src_by_id[b.id].iter_polygons()]
        for p, q in zip(b.iter_polygons(), src_by_id[b.id].iter_polygons(), strict=True):
            assert np.array_equal(p.exterior.coords, q.exterior.coords)
    rep = json.loads((out / "report.json").read_text())
    assert rep["buildings_textured"] == len(back)


@pytest.mark.slow
def test_drive_with_gnss_ins_errors_is_oriented_and_textured_to_the_bars(tmp_path):
    """`citytherm run` with refinement on a drive with the default GNSS/INS error model (bias,
    boresight of degrees, vibration, delay): calibrate, orient the sequence, refine per building.
    The refined poses reproject the buildings below a pixel and the textures meet the issue's
    bars (RMSE ≤ 0.45 K, misregistration ≤ 0.5 texel) with margin; without refinement they are
    far off."""
    from db.citygml.writer import write_citygml
    from tests.unit.orientation_scenes import reprojection_rms
    from workers.pipeline.geometry.pose import Pose
    from workers.pipeline.synth import procedural_block
    from workers.synth_eval import orientation_accuracy

    blds = procedural_block(6, seed=1)
    gml = tmp_path / "city.gml"
    write_citygml(gml, blds, srs_name=blds[0].srs_name)
    opts = SynthOptions(platform="drive", n_frames=24, seed=1, buildings=2, model_path=str(gml))
    res = synthesize(blds, opts)
    pkg = write_synthetic_package(res, tmp_path / "seq")
    summary = run_job(gml, pkg, tmp_path / "out", RunOptions.build(refine=True, display=False))
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["calibration"]["accepted"] is True
    so = rep["sequence_orientation"]
    assert so["run"] is True and so["frames_oriented"] == 24 and "orient" in rep["timings_s"]
    assert summary.orientation == so
    doc = json.loads((tmp_path / "out" / "orientation.json").read_text())
    by_id = {b.id: b for b in res.buildings}
    errs, status = [], []
    for f in doc["frames"]:
        T = res.truth.poses[f["index"]]
        for r in f["refined"]:
            pose = Pose.from_dict(r)
            errs.append(reprojection_rms(res.manifest.camera, by_id[r["building"]], pose, T))
            status.append(r["status"])
    errs, status = np.array(errs), np.array(status)
    ok = np.isfinite(errs)
    assert ok.sum() > 20 and np.mean(status[ok] == "refined") > 0.9
    assert np.mean(errs[ok & (status == "refined")] < 1.0) > 0.95
    acc = texture_accuracy(tmp_path / "out", res)
    assert acc["rmse_k"] < 0.35 and acc["misregistration_median_texel"] < 0.3, acc
    assert orientation_accuracy(tmp_path / "out", res)["refined_position_error_median_m"] < 0.05
