"""The split-half check (`citytherm run --split-half`): the pure comparison of two half-textures
(`workers.pipeline.texture.split_half`) recovers known sub-texel shifts and value differences; the
job-level orchestration (`workers.split_half`) textures alternate frames with the poses the units
used, leaves the job's outputs unchanged, and on synthetic drives its figure agrees with the truth:
small with true poses, the geometric shift when one half's poses are biased."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from tests.unit.texture_scene import box_building, look_at, render
from workers.job import RunOptions
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import MemoryFrames, Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.plan import plan_units
from workers.pipeline.results import BuildingResult, FramePose
from workers.pipeline.texture.split_half import (
    SplitHalfOptions,
    split_half_agreement,
    summarize,
)
from workers.pipeline.texture.texel import texel_grid
from workers.pipeline.units import BuildingUnit
from workers.split_half import compare_halves, half_unit, split_half_report, textured_poses

CAM = Camera(320, 256, 300.0, 300.0, 159.5, 127.5, k1=-0.05)


def _field(x: np.ndarray, y: np.ndarray, seed: int = 1) -> np.ndarray:
    """A smooth random temperature field (K) at raster positions: a sum of 60 plane waves, exact at
    any sub-texel position."""
    rng = np.random.default_rng(seed)
    fr = rng.uniform(0.05, 0.6, (60, 2)) * rng.choice([-1, 1], (60, 2))
    ph = rng.uniform(0, 2 * np.pi, 60)
    am = rng.uniform(0.2, 1.0, 60)
    return 290.0 + sum(am[k] * np.sin(fr[k, 0] * x + fr[k, 1] * y + ph[k]) for k in range(60))


def _pair(d: tuple[float, float], H: int = 96, W: int = 160, noise: float = 0.03) -> tuple[np.ndarray, ...]:
    """Rasters `a`, `b` with `b(x) = a(x − d)` plus noise, `a` with an unobserved corner."""
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    rng = np.random.default_rng(7)
    a = (_field(xx, yy) + rng.normal(0, noise, (H, W))).astype(np.float32)
    b = (_field(xx - d[0], yy - d[1]) + rng.normal(0, noise, (H, W))).astype(np.float32)
    a[:12, :40] = np.nan
    return a, b


@pytest.mark.parametrize("d", [(0.3, 0.0), (1.7, 0.0), (0.0, -0.3), (1.7, -0.4), (-0.8, 1.3)])
def test_known_subtexel_shifts_are_recovered_tile_by_tile(d: tuple[float, float]) -> None:
    a, b = _pair(d)
    got = split_half_agreement(a, b, texel_size_m=0.01)
    assert len(got.tiles) >= 12  # 15 tiles of 32 × 32, the one with the unobserved corner left out
    for t in got.tiles:
        assert t.dx == pytest.approx(d[0], abs=0.05) and t.dy == pytest.approx(d[1], abs=0.05), t
        assert t.correlation > 0.9
        assert t.agrees == (np.hypot(*d) <= 0.5)
    doc = summarize([got])
    assert doc["median_shift_texels"] == pytest.approx(np.hypot(*d), abs=0.02)
    assert doc["median_shift_m"] == pytest.approx(0.01 * np.hypot(*d), abs=2e-4)
    assert doc["median_dx_texels"] == pytest.approx(d[0], abs=0.02)


def test_equal_halves_with_an_offset_agree_in_place_and_report_the_value_difference() -> None:
    a, _ = _pair((0.0, 0.0), noise=0.0)
    got = split_half_agreement(a, a + np.float32(0.5), texel_size_m=0.1)
    doc = got.to_dict(with_tiles=True)
    assert doc["tiles"] == len(doc["tile_shifts"]) >= 12 and doc["agree_share"] == 1.0
    assert doc["median_shift_texels"] < 0.01
    assert doc["median_abs_diff_k"] == pytest.approx(0.5, abs=1e-4)
    assert doc["rms_diff_k"] == pytest.approx(0.5, abs=1e-4)
    assert doc["mean_diff_k"] == pytest.approx(0.5, abs=1e-4)
    assert doc["texels_common"] == int(np.isfinite(a).sum())


def test_unobserved_flat_and_unrelated_tiles() -> None:
    a, b = _pair((0.0, 0.0))
    b[:, 64:] = np.nan  # right half of the raster not observed by b
    got = split_half_agreement(a, b, 0.1)
    assert got.tiles and all(t.col + 32 <= 64 for t in got.tiles)
    flat = np.full((64, 64), 285.0, np.float32)
    nothing = split_half_agreement(flat, flat + np.float32(0.01), 0.1)
    assert nothing.tiles == () and summarize([nothing])["median_shift_texels"] is None
    rng = np.random.default_rng(3)
    x, y = (rng.normal(285, 1, (96, 96)).astype(np.float32) for _ in range(2))
    noise = split_half_agreement(x, y, 0.1)
    assert len(noise.tiles) == 9 and not any(t.agrees for t in noise.tiles)
    assert all(abs(t.correlation) < 0.3 for t in noise.tiles)
    assert len(split_half_agreement(x, y, 0.1, tile=48).tiles) == 4
    assert len(split_half_agreement(x, y, 0.1, options=SplitHalfOptions(tile=48)).tiles) == 4
    with pytest.raises(ValueError, match="one grid"):
        split_half_agreement(a, b[:, :10], 0.1)


def test_surfaces_pool_into_buildings_and_jobs() -> None:
    a1, b1 = _pair((0.3, 0.0))
    one = split_half_agreement(a1, b1, texel_size_m=0.1)
    a, b = _pair((1.2, 0.0))
    b = b + np.float32(0.2)
    two = split_half_agreement(a, b, texel_size_m=0.02)
    doc = summarize([one, two])
    assert doc["tiles"] == len(one.tiles) + len(two.tiles)
    shifts = [t.shift for t in one.tiles] + [t.shift for t in two.tiles]
    metres = [t.shift * 0.1 for t in one.tiles] + [t.shift * 0.02 for t in two.tiles]
    assert doc["median_shift_texels"] == pytest.approx(np.median(shifts), abs=1e-4)
    assert doc["median_shift_m"] == pytest.approx(np.median(metres), abs=1e-5)
    n = one.texels_common + two.texels_common
    assert doc["rms_diff_k"] == pytest.approx(np.sqrt((one.rms_diff**2 * one.texels_common
                                                       + two.rms_diff**2 * two.texels_common) / n), rel=1e-3)
    exact = np.median(np.abs(np.concatenate([(b - a)[np.isfinite(a)], (b1 - a1)[np.isfinite(a1)]])))
    assert doc["median_abs_diff_k"] == pytest.approx(exact, rel=0.02)  # from the histograms


# --- the orchestration, on an analytic box building (fast) ---


def _box_unit(n: int = 10) -> tuple[BuildingUnit, list[Pose]]:
    b = box_building("B1", 0, 0, 12, 8, 7, holes=True)
    poses = [look_at([-4 + 2.0 * k, -14, 1.6], [-1 + 2.0 * k, 0, 4.0]) for k in range(n)]
    frames = {i: render(CAM, p, [b]) for i, p in enumerate(poses)}
    (unit,) = plan_units([b], CAM, poses, MemoryFrames(frames), Radiometry())
    return unit, poses


def test_halves_take_alternate_frames_with_the_poses_the_unit_textured_with() -> None:
    unit, poses = _box_unit(6)
    moved = Pose(poses[3].R_world_from_cam, poses[3].center + 0.5)
    result = BuildingResult(
        "B1", None, (), Radiometry(), (),
        poses=(FramePose(3, "B1", moved, "refined"), FramePose(4, "B1", poses[4], "prior")),
    )
    used = textured_poses(unit, result)
    assert used[3] is moved and used[4] is unit.poses[unit.frames.index(4)]
    even, odd = half_unit(unit, 0, used), half_unit(unit, 1, used)
    assert even.frames == unit.frames[0::2] and odd.frames == unit.frames[1::2]
    assert odd.poses[odd.frames.index(3)] is moved
    assert even.options.refine is None and odd.options.refine is None and even.sequence is None
    assert even.times == unit.times[0::2] and even.building is unit.building


def test_analytic_drive_halves_agree_and_a_biased_half_shows_its_bias() -> None:
    unit, _ = _box_unit(10)
    poses = dict(zip(unit.frames, unit.poses, strict=True))
    same = compare_halves(unit, poses)
    wall = next(s for s in same.surfaces if s.polygon_id == "B1_w0")
    assert same.frames_even == same.frames_odd == 5
    doc = summarize([wall.agreement])
    assert doc["tiles"] >= 4 and doc["median_shift_texels"] < 0.1, doc
    grid = texel_grid(next(p for p in unit.building.iter_polygons() if p.id == "B1_w0"), "B1",
                      unit.options.texel)
    assert grid is not None
    d = 0.2 * grid.s_axis  # the odd half's poses 0.2 m off along the wall
    odd = {f: Pose(p.R_world_from_cam, p.center + d) for f, p in poses.items()}
    biased = compare_halves(unit, poses, odd)
    got = summarize([next(s for s in biased.surfaces if s.polygon_id == "B1_w0").agreement])
    expected = (d @ grid.s_axis / grid.size, -(d @ grid.t_axis) / grid.size)  # (2, 0) texels
    assert got["median_dx_texels"] == pytest.approx(expected[0], abs=0.1), got
    assert got["median_dy_texels"] == pytest.approx(expected[1], abs=0.1), got
    assert got["agree_share"] == 0.0


class _Broken:
    """A frame source whose frames are gone."""

    def load(self, index: int) -> np.ndarray:
        raise OSError(f"frame {index} gone")


def test_the_job_block_is_strict_json_and_reports_a_building_that_failed() -> None:
    unit, _ = _box_unit(6)
    broken = replace(unit, frame_source=_Broken())
    result = BuildingResult("B1", None, (), Radiometry(), ())
    steps: list[tuple[int, int]] = []
    doc = split_half_report([unit, broken], [result], progress=lambda s, d, t: steps.append((d, t)))
    text = json.dumps(doc, allow_nan=False)  # no NaN anywhere: null instead
    assert steps == [(0, 2), (1, 2), (2, 2)]
    ok, bad = json.loads(text)["buildings"]
    assert ok["frames_even"] == ok["frames_odd"] == 3 and ok["tiles"] >= 2 and ok["surfaces"]
    assert "frame" in bad["error"] and "tiles" not in bad
    assert doc["tiles"] == ok["tiles"]  # the failed building adds nothing
    assert split_half_report([unit], [])["buildings"] == []  # units without a result are left out


def test_the_option_round_trips_and_defaults_off() -> None:
    assert RunOptions().split_half is False
    opts = RunOptions.build(refine=False, split_half=True)
    assert RunOptions.from_dict(json.loads(json.dumps(opts.to_dict()))).split_half is True


# --- end to end: `citytherm run --split-half` on a synthetic drive with true poses ---


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    from db.citygml.reader import read_model
    from db.synth_files import write_synthetic_package
    from services.cli import run_cmd
    from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
    from workers.run import run_job

    folder = tmp_path_factory.mktemp("splithalf")
    _, buildings = read_model(BUNDLED_MODEL)
    res = synthesize(buildings, SynthOptions(
        n_frames=20, seed=3, buildings=2, frame_interval_s=0.2, errors=ErrorOptions(enabled=False),
        model_path=str(BUNDLED_MODEL)))  # fmt: skip
    pkg = write_synthetic_package(res, folder / "seq")
    ids = tuple(res.truth.cluster)
    app = typer.Typer()
    run_cmd.register(app)

    @app.callback()
    def _root() -> None:
        """test root"""

    args = ["run", str(BUNDLED_MODEL), str(pkg), "-o", str(folder / "split"), "--resolution", "10",
            "--no-refine", "--no-display", "--buildings", ",".join(ids), "--split-half"]
    cli = CliRunner().invoke(app, args, env={"COLUMNS": "200"})
    assert cli.exit_code == 0, cli.output
    plain = run_job(BUNDLED_MODEL, pkg, folder / "plain",
                    RunOptions.build(resolution_px_per_m=10, refine=False, display=False, buildings=ids))
    return res, pkg, folder, cli.output, plain


@pytest.mark.slow
def test_split_half_report_on_a_true_pose_drive_agrees_with_the_truth(drive: tuple) -> None:
    from workers.synth_eval import texture_accuracy

    res, _, folder, output, _ = drive
    rep = json.loads((folder / "split" / "report.json").read_text())
    sh = rep["split_half"]
    assert sh["run"] is True and sh["options"]["tile"] == 32 and "split_half" in rep["timings_s"]
    assert sh["tiles"] >= 15 and sh["buildings"], sh
    assert sh["median_shift_texels"] <= 0.3 and sh["agree_share"] >= 0.8, sh
    assert sh["median_shift_m"] <= 0.03  # texels of 0.1 m, or coarser where the frames see coarsely
    assert 0 < sh["median_abs_diff_k"] < 0.3 and sh["rms_diff_k"] < 0.5, sh
    for b in sh["buildings"]:
        assert {"id", "frames_even", "frames_odd", "tiles", "median_shift_texels"} <= set(b)
        for s in b["surfaces"]:
            assert s["texels_common"] > 0 and s["texel_size_m"] >= 0.1 - 1e-9
    truth = texture_accuracy(folder / "split", res)["misregistration_median_texel"]
    assert abs(sh["median_shift_texels"] - truth) < 0.15, (sh["median_shift_texels"], truth)
    assert "split half: median tile shift" in output


@pytest.mark.slow
def test_the_flag_leaves_the_outputs_unchanged(drive: tuple) -> None:
    _, _, folder, _, plain = drive
    split, base = folder / "split", folder / "plain"
    tiles = sorted(p.name for p in (base / "textures").iterdir())
    assert tiles and tiles == sorted(p.name for p in (split / "textures").iterdir())
    for name in tiles:
        assert (split / "textures" / name).read_bytes() == (base / "textures" / name).read_bytes(), name
    for name in ("textured.gml", "orientation.json"):
        assert (split / name).read_bytes() == (base / name).read_bytes(), name
    rs, rb = (json.loads((f / "report.json").read_text()) for f in (split, base))
    assert "split_half" not in rb and plain.split_half is None
    for key in ("buildings", "calibration", "sequence_orientation", "texel"):
        strip = lambda bs: [{k: v for k, v in b.items() if k != "timings_s"} for b in bs]  # noqa: E731
        assert (strip(rs[key]) if key == "buildings" else rs[key]) == (
            strip(rb[key]) if key == "buildings" else rb[key])  # fmt: skip


@pytest.mark.slow
def test_a_half_with_biased_poses_shows_the_geometric_shift(drive: tuple) -> None:
    """The odd half's poses 0.2 m off along a facade: the split-half shift on that facade is the
    bias in texels of its grid, (d·s, −d·t) / texel size."""
    from workers.job import calibrate, ingest, orient, plan
    from workers.pipeline.synth import BUNDLED_MODEL

    _, pkg, folder, _, _ = drive
    rep = json.loads((folder / "split" / "report.json").read_text())
    surfaces = [(b["id"], s) for b in rep["split_half"]["buildings"] for s in b.get("surfaces", [])]
    building, best = max(surfaces, key=lambda bs: bs[1]["tiles"])
    opts = RunOptions.build(resolution_px_per_m=10, refine=False, buildings=(building,))
    ing = ingest(BUNDLED_MODEL, pkg, opts)
    cal = calibrate(ing, opts)
    (unit,) = plan(ing, cal, orient(ing, cal, opts), opts).units
    part = next(p for p in unit.building.iter_buildings() if any(q.id == best["id"] for q in p.polygons))
    grid = texel_grid(next(q for q in part.polygons if q.id == best["id"]), part.id, unit.options.texel)
    assert grid is not None
    poses = dict(zip(unit.frames, unit.poses, strict=True))
    for d in (0.2 * grid.s_axis, 0.05 * grid.s_axis + 0.1 * grid.t_axis):
        odd = {f: Pose(p.R_world_from_cam, p.center + d) for f, p in poses.items()}
        check = compare_halves(unit, poses, odd)
        got = summarize([next(s for s in check.surfaces if s.polygon_id == best["id"]).agreement])
        expected = (d @ grid.s_axis / grid.size, -(d @ grid.t_axis) / grid.size)
        assert got["median_dx_texels"] == pytest.approx(expected[0], abs=0.15), (got, expected)
        assert got["median_dy_texels"] == pytest.approx(expected[1], abs=0.15), (got, expected)
        assert got["median_shift_m"] == pytest.approx(float(np.linalg.norm(d)), abs=0.015)


def test_the_report_block_is_documented() -> None:
    root = Path(__file__).resolve().parents[2]
    assert "--split-half" in (root / "README.md").read_text()
    assert "split_half" in (root / "docs" / "results-format.md").read_text()


def _halves_of(
    field: np.ndarray, d: tuple[float, float], noise: float, blur: float, seed: int
) -> tuple[np.ndarray, ...]:
    """Two noisy halves of one texture: `a = field + n_a`, `b(x) = field(x − d) + n_b`, the noises
    independent, Gaussian, `noise` K after a Gaussian blur of `blur` texels (a half-texture's
    noise is correlated over the pixel footprint)."""
    rng = np.random.default_rng(seed)
    H, W = field.shape
    out = []
    for shift in ((0.0, 0.0), d):
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        img = cv2.remap(field.astype(np.float32), xx - np.float32(shift[0]), yy - np.float32(shift[1]),
                        cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)  # fmt: skip
        n = cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), blur)
        out.append(img + n * np.float32(noise / n.std()))
    return out[0], out[1]


@pytest.mark.parametrize("d", [(0.0, 0.0), (0.25, -0.2)])
def test_periodic_texture_is_not_matched_a_period_away(d: tuple[float, float]) -> None:
    """A periodic texture (bricks, a window grid, period 11 × 9 texels), part of the tile left
    unobserved: the normalised cross-power spectrum has peaks a period apart, refining only
    from its highest one reported whole periods (a periodic roof on the NRW drive: 6 texels);
    the shift must be the one the halves share."""
    yy, xx = np.mgrid[0:96, 0:128].astype(float)
    wobble = 0.4 * np.sin(xx / 17.0)
    field = 280.0 + 0.5 * np.sin(2 * np.pi * xx / 11.0) * np.sin(2 * np.pi * yy / 9.0 + wobble)
    a, b = _halves_of(field, d, noise=0.05, blur=1.0, seed=3)
    a[60:, :30] = np.nan  # a half sees part of the surface only
    b[:10, 90:] = np.nan
    got = split_half_agreement(a, b, texel_size_m=0.1)
    assert len(got.tiles) >= 6
    for t in got.tiles:
        assert t.dx == pytest.approx(d[0], abs=0.15) and t.dy == pytest.approx(d[1], abs=0.15), t
        assert t.correlation > 0.9

