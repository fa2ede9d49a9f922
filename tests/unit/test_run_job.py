"""`citytherm run` end to end on an analytic scene: the results folder as the spec says."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from services.cli import app
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, field, look_at
from workers.job import RunError, RunOptions
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import ParameterizedTexture
from workers.pipeline.geometry.manifest import MemoryFrames, Radiometry
from workers.pipeline.plan import plan_units
from workers.pipeline.units import UnitOptions, run_building_unit
from workers.run import run_job

CAM = Camera(240, 192, 220.0, 220.0, 119.5, 95.5, k1=-0.05)
NO_REFINE = UnitOptions(refine=None)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    buildings = [box_building("B1", 0, 0, 12, 8, 7, holes=True), box_building("B2", 16, 0, 24, 6, 5)]
    buildings.append(box_building("FAR", 500, 500, 505, 505, 5))  # never seen
    poses = [look_at([-3 + 3.0 * k, -15, 1.6], [0 + 3.0 * k, 0, 3.5]) for k in range(9)]
    gml, pkg = write_scene(folder, buildings, CAM, poses)
    return folder, gml, pkg, buildings, poses


@pytest.fixture(scope="module")
def job(scene):
    folder, gml, pkg, _, _ = scene
    out = folder / "out"
    return out, run_job(gml, pkg, out, RunOptions.build(resolution_px_per_m=10, refine=False))


def test_results_folder_has_the_spec_files_and_valid_citygml_with_the_same_ids(scene, job):
    _, _gml, _, buildings, _ = scene
    out, summary = job
    for name in ("textured.gml", "orientation.json", "report.json", "textures/B1_0.png", "textures/B2_0.png"):
        assert (out / name).is_file(), name
    assert (out / "textures/B1_0-display.png").is_file()
    assert validate_citygml2(out / "textured.gml") == []
    _header, back = read_model(out / "textured.gml")
    assert [b.id for b in back] == ["B1", "B2"]  # the textured buildings, FAR was never seen
    src = {b.id: b for b in buildings}
    for b in back:
        assert [p.id for p in b.iter_polygons()] == [p.id for p in src[b.id].iter_polygons()]
        assert [r.id for p in b.iter_polygons() for r in p.rings] == [
            r.id for p in src[b.id].iter_polygons() for r in p.rings
        ]
        themes = sorted(a.theme for a in b.appearances)
        assert themes == ["thermal-ir", "thermal-ir-display"]
    assert {r.building_id for r in summary.results} == {"B1", "B2"}


def test_tiles_and_texture_coordinates_read_back_to_the_ground_truth(job):
    out, _ = job
    _, back = read_model(out / "textured.gml")
    rad = Radiometry("K", 0.01, 0.0)
    checked = 0
    for b in back:
        app = next(a for a in b.appearances if a.theme == "thermal-ir")
        polys = {p.id: p for p in b.iter_polygons()}
        for tex in app.surface_data:
            assert isinstance(tex, ParameterizedTexture) and tex.mime_type == "image/png"
            dn = cv2.imread(str(out / tex.image_uri), cv2.IMREAD_UNCHANGED)
            assert dn.dtype == np.uint16 and dn.ndim == 2
            H, W = dn.shape
            for target in tex.targets:
                poly = polys[target.polygon_id]
                ext = poly.exterior
                st = target.ring_coords[ext.id]
                assert st.shape == (len(ext.coords), 2)
                # affine map plane -> tile raster from three ring vertices, then sample the tile
                X = np.c_[st[:, 0] * W, (1 - st[:, 1]) * H]
                A, *_ = np.linalg.lstsq(np.c_[ext.coords, np.ones(len(ext.coords))], X, rcond=None)
                rng = np.random.default_rng(0)
                w = rng.dirichlet(np.ones(len(ext.coords) - 1), size=200)
                pts = w @ ext.coords[:-1]
                xy = np.c_[pts, np.ones(len(pts))] @ A
                vals = dn[np.floor(xy[:, 1]).astype(int), np.floor(xy[:, 0]).astype(int)]
                seen = vals > 0
                if seen.sum() < 20:
                    continue
                # texel centres are within half a texel diagonal: compare with the field's variation
                err = rad.physical(vals[seen]) - field(pts[seen])
                assert np.median(np.abs(err)) < 0.3, poly.id
                checked += 1
    assert checked >= 3


def test_orientation_and_report_documents(scene, job):
    _, _, _, _, poses = scene
    out, _ = job
    doc = json.loads((out / "orientation.json").read_text())
    assert doc["format"] == "citytherm-orientation/1"
    assert len(doc["frames"]) == len(poses)
    for f, p in zip(doc["frames"], poses, strict=True):
        assert np.allclose(f["prior"]["center"], p.center, atol=1e-6)
        assert np.allclose(f["prior"]["rotation"], p.R_world_from_cam, atol=1e-9)
        assert f["refined"] == []
    assert doc["mounting"]["time_delay_s"] == 0.0
    rep = json.loads((out / "report.json").read_text())
    assert set(rep["timings_s"]) == {"ingest", "plan", "units", "write"}
    assert rep["calibration"] == {"run": False}  # no refinement: no calibration
    b1 = next(b for b in rep["buildings"] if b["id"] == "B1")
    w0 = next(s for s in b1["surfaces"] if s["id"] == "B1_w0")
    assert w0["texels_observed"] / w0["texels_total"] > 0.9
    assert 0.01 < w0["mean_resolution_m"] < 0.2 and 0 <= w0["mean_view_angle_deg"] < 80
    assert abs(w0["temperature"]["mean"] - 286) < 5
    north = next(s for s in b1["surfaces"] if s["id"] == "B1_w2")
    assert north["texels_observed"] == 0 and north["mean_resolution_m"] is None


def test_units_are_picklable_and_runs_are_reproducible(scene):
    _, _, _, buildings, poses = scene
    frames = {i: np.full((CAM.height, CAM.width), 280.0, np.float32) for i in range(len(poses))}
    units = plan_units(buildings, CAM, poses, MemoryFrames(frames), Radiometry(), options=NO_REFINE)
    assert [u.building.id for u in units] == ["B1", "B2"]
    assert [o.id for o in units[0].occluders] == ["B2"]
    u2 = pickle.loads(pickle.dumps(units[0]))
    a, b = run_building_unit(units[0]), run_building_unit(u2)
    assert [t.name for t in a.tiles] == [t.name for t in b.tiles]
    assert all(np.array_equal(x.dn, y.dn) for x, y in zip(a.tiles, b.tiles, strict=True))
    observed = [s for s in a.surfaces if s.texels_observed]
    assert observed and all(s.temperature["median"] == pytest.approx(280.0) for s in observed)
    assert {s.polygon_id for s in a.surfaces} == {p.id for p in buildings[0].iter_polygons()}


def test_bad_input_names_what_is_wrong(scene, tmp_path):
    _, gml, pkg, _, _ = scene
    with pytest.raises(RunError, match="NOPE"):
        run_job(gml, pkg, tmp_path / "o", RunOptions.build(buildings=("NOPE",), refine=False))
    with pytest.raises(RunError, match="city model not found"):
        run_job(tmp_path / "missing.gml", pkg, tmp_path / "o")


@pytest.mark.slow
def test_cli_with_two_workers_gives_the_same_textures(scene, job, tmp_path):
    _, gml, pkg, _, _ = scene
    out1, _ = job
    res = CliRunner().invoke(
        app, ["run", str(gml), str(pkg), "-o", str(tmp_path / "o2"), "--workers", "2", "--no-refine"]
    )
    assert res.exit_code == 0, res.output
    assert "total: 2" in res.output
    for name in ("textures/B1_0.png", "textures/B2_0.png"):
        a = cv2.imread(str(out1 / name), cv2.IMREAD_UNCHANGED)
        b = cv2.imread(str(tmp_path / "o2" / name), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(a, b)


def test_a_failing_building_is_reported_and_the_others_are_written(scene, tmp_path, monkeypatch):
    import workers.job as job_module

    _, gml, pkg, _, _ = scene
    real = job_module.run_building_unit

    def flaky(unit):
        if unit.building.id == "B2":
            raise ValueError("broken geometry")
        return real(unit)

    monkeypatch.setattr(job_module, "run_building_unit", flaky)
    summary = run_job(gml, pkg, tmp_path / "o", RunOptions.build(display=False, refine=False))
    assert [f.building_id for f in summary.failures] == ["B2"]
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["failed"] == [{"id": "B2", "error": "ValueError: broken geometry"}]
    assert [b["id"] for b in rep["buildings"]] == ["B1"]
    _, back = read_model(tmp_path / "o" / "textured.gml")
    assert [b.id for b in back] == ["B1"]


def test_8bit_frames_keep_their_values_in_the_tiles(tmp_path):
    from db.sequence_package import open_package, write_package
    from workers.pipeline.results import output_radiometry

    src = tmp_path / "src"
    src.mkdir()
    b = [box_building("B8", 0, 0, 6, 4, 4)]
    poses = [look_at([3, -10, 1.6], [3, 0, 2.0])]
    gml, pkg = write_scene(src, b, CAM, poses)
    m = open_package(pkg).manifest
    frames8 = [np.full((CAM.height, CAM.width), 200, np.uint8)]
    pkg8 = write_package(tmp_path / "seq8", m, frames8)
    with open_package(pkg8) as p8:
        assert output_radiometry(p8.manifest.radiometry, p8.frames.raw(0).dtype) == Radiometry(
            m.radiometry.unit, 1.0, 0.0
        )
    run_job(gml, pkg8, tmp_path / "o8", RunOptions.build(display=False, refine=False))
    dn = cv2.imread(str(tmp_path / "o8" / "textures" / "B8_0.png"), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(dn).tolist()) == {0, 200}


def test_a_texel_resolution_finer_than_the_frames_can_give_is_warned_about(scene):
    from workers.job import calibrate, ingest, orient, plan

    _, gml, pkg, _, _ = scene

    def planned(options):
        ingested = ingest(gml, pkg, options)
        calibrated = calibrate(ingested, options)
        return plan(ingested, calibrated, orient(ingested, calibrated, options), options)

    fine = planned(RunOptions.build(resolution_px_per_m=200, refine=False))
    ok = planned(RunOptions.build(resolution_px_per_m=10, refine=False))
    assert fine.warning is not None and "--resolution" in fine.warning
    assert ok.warning is None


def test_refinement_is_reported_and_a_failing_refinement_keeps_the_priors(scene, tmp_path, monkeypatch):
    """The refiner's answer (here a stand-in) goes to orientation.json; when it raises, the
    building is textured with its priors."""
    _, gml, pkg, _, poses = scene

    class Refined:
        def __init__(self, frame, pose, status):
            self.frame, self.pose, self.status, self.rms_px, self.matches = frame, pose, status, 0.4, 12

    def refine_building(camera, building, raycaster, frames, frame_source, prior, accuracy, **_):
        if building.id == "B2":
            raise RuntimeError("no edges")
        return {f: Refined(f, prior[f], "refined" if f % 2 == 0 else "prior") for f in frames}

    # no calibration: the stand-in must see the manifest's priors
    options = RunOptions.build(refine=True, calibrate=False, display=False)
    run_job(gml, pkg, tmp_path / "r", options, refiner=refine_building)
    doc = json.loads((tmp_path / "r" / "orientation.json").read_text())
    entries = [(f["index"], r["building"], r["status"]) for f in doc["frames"] for r in f["refined"]]
    b1 = [e for e in entries if e[1] == "B1"]
    assert b1 and all(st == ("refined" if i % 2 == 0 else "prior") for i, _, st in b1)
    assert all(st == "prior" for _, b, st in entries if b == "B2")  # failed: priors kept
    ref = next(r for f in doc["frames"] for r in f["refined"] if r["status"] == "refined")
    assert ref["rms_px"] == 0.4 and ref["matches"] == 12
    assert np.allclose(
        ref["center"], poses[next(f["index"] for f in doc["frames"] if ref in f["refined"])].center
    )
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert rep["refine"] is True and {b["id"] for b in rep["buildings"]} == {"B1", "B2"}


def test_results_folder_from_in_memory_results_as_the_service_writes_it(scene, tmp_path):
    from db.results_folder.write import write_results_folder
    from db.sequence_package import open_package
    from workers.pipeline.texture.texel import TexelOptions

    _, _, pkg_path, buildings, poses = scene
    pkg = open_package(pkg_path)
    units = plan_units(buildings, CAM, poses, pkg.frames, pkg.manifest.radiometry, options=NO_REFINE)
    results = [run_building_unit(u) for u in units]
    write_results_folder(
        tmp_path / "svc",
        buildings=buildings,
        results=results,
        manifest=pkg.manifest,
        priors=poses,
        srs_name="EPSG:25832",
        theme="thermal-ir",
        texel=TexelOptions(resolution_px_per_m=10.0),
    )
    for name in (
        "textured.gml",
        "orientation.json",
        "report.json",
        "textures/B1_0.png",
        "textures/B1_0-display.png",
    ):
        assert (tmp_path / "svc" / name).is_file(), name
    assert validate_citygml2(tmp_path / "svc" / "textured.gml") == []
    rep = json.loads((tmp_path / "svc" / "report.json").read_text())
    assert [b["id"] for b in rep["buildings"]] == ["B1", "B2"] and "write" in rep["timings_s"]


def test_only_buildings_within_reach_of_the_cameras_are_kept():
    from workers.pipeline.plan import near_buildings

    near = box_building("NEAR", 0, 0, 5, 5, 5)
    far = box_building("FAR", 900, 900, 905, 905, 5)
    kept, ids = near_buildings(iter([near, far]), [look_at([2, -10, 1.6], [2, 0, 2])], 300.0)
    assert [b.id for b in kept] == ["NEAR"] and ids == {"NEAR", "FAR"}


def test_refinement_calibrates_the_sequence_first_and_reports_the_mounting(tmp_path: Path) -> None:
    """A small synthetic drive (error-free poses) with refinement: the calibrate stage runs, its
    block goes to report.json, the estimated mounting to orientation.json, whose priors stay the
    manifest-only ones."""
    from db.citygml.writer import write_citygml
    from db.sequence_package import open_package
    from db.synth_files import write_synthetic_package as write_synth
    from workers.pipeline.geometry.georef import prior_poses
    from workers.pipeline.synth import ErrorOptions, SynthOptions, procedural_block, synthesize

    blds = procedural_block(6, seed=1)
    res = synthesize(blds, SynthOptions(n_frames=8, seed=1, buildings=2, errors=ErrorOptions(enabled=False)))
    gml = tmp_path / "city.gml"
    write_citygml(gml, blds, srs_name=blds[0].srs_name)
    pkg = write_synth(res, tmp_path / "seq")
    stages: list[str] = []
    summary = run_job(
        gml, pkg, tmp_path / "out", RunOptions.build(resolution_px_per_m=2, refine=True, display=False),
        progress=lambda stage, done, total: stages.append(stage),
    )
    assert "calibrate" in stages and stages.index("calibrate") < stages.index("plan")
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    cal = rep["calibration"]
    assert cal["run"] is True and isinstance(cal["accepted"], bool)
    assert len(cal["gnss_offset_m"]) == 3 and len(cal["boresight_correction_deg"]) == 3
    assert "calibrate" in rep["timings_s"] and rep["calibrate"] is True
    assert summary.calibration == cal
    doc = json.loads((tmp_path / "out" / "orientation.json").read_text())
    mnt = doc["mounting"]
    assert isinstance(mnt["time_delay_s"], float) and np.isfinite(mnt["time_delay_s"])
    assert np.all(np.isfinite(mnt["boresight_deg"])) and np.all(np.isfinite(mnt["lever_arm_m"]))
    manifest = open_package(pkg).manifest
    if cal["accepted"]:  # error-free poses: the estimate stays near the manifest's mounting
        assert np.allclose(mnt["boresight_deg"], manifest.mounting.boresight_deg, atol=0.5)
        assert np.allclose(mnt["lever_arm_m"], manifest.mounting.lever_arm_m, atol=0.5)
        assert abs(mnt["time_delay_s"]) < 0.05
    for f, p in zip(doc["frames"], prior_poses(manifest, blds[0].srs_name), strict=True):
        assert np.allclose(f["prior"]["center"], p.center, atol=1e-6)


def test_cli_no_calibrate_turns_the_stage_off(
    scene: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import services.cli.run_cmd as run_cmd
    from workers.run import RunSummary

    _, gml, pkg, _, _ = scene
    seen: list[RunOptions] = []

    def fake_run_job(
        city: Path, package: Path, out: Path, options: RunOptions, progress: object = None
    ) -> RunSummary:
        seen.append(options)
        return RunSummary(tmp_path, 0, 0, [], [], {}, {}, options.refine, calibration={"run": False})

    monkeypatch.setattr(run_cmd, "run_job", fake_run_job)
    for flags, want in (([], True), (["--no-calibrate"], False)):
        res = CliRunner().invoke(app, ["run", str(gml), str(pkg), "-o", str(tmp_path / "o"), *flags])
        assert res.exit_code == 0, res.output
        assert seen[-1].refine is True and seen[-1].calibrate is want and seen[-1].orient is True
    assert "calibration: off" in res.output
    res = CliRunner().invoke(app, ["run", str(gml), str(pkg), "-o", str(tmp_path / "o"), "--no-orient"])
    assert res.exit_code == 0, res.output
    assert seen[-1].orient is False and seen[-1].calibrate is True
