"""`citytherm run` on a synthetic drive around real buildings with error-free poses: texture
RMSE, misregistration and coverage against the generator's ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from services.runner import RunOptions, run_job
from services.synth_eval import texture_accuracy
from workers.pipeline.synth import (
    BUNDLED_MODEL,
    ErrorOptions,
    SynthOptions,
    synthesize,
    write_synthetic_package,
)


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
        BUNDLED_MODEL, pkg, out, RunOptions(resolution_px_per_m=10, refine=False, display=False)
    )
    return res, out, summary


@pytest.mark.slow
def test_error_free_drive_meets_the_texture_bars_with_margin(drive):
    res, out, summary = drive
    acc = texture_accuracy(out, res)
    assert acc["texels_observed"] > 50000, acc
    assert acc["rmse_k"] < 0.3, acc  # bar 0.35 K
    assert acc["misregistration_median_texel"] < 0.2, acc  # bar 0.3 texel
    assert acc["coverage"] > 0.95, acc  # bar 95 % (a short drive: 20 frames)
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
