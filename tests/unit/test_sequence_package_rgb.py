"""The optional second (RGB) camera of a sequence package: round trip, refusals, synth."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from db.sequence_package import PackageError, open_package, write_package
from db.synth_files import write_synthetic_package
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import (
    Accuracy,
    FrameRecord,
    Mounting,
    Radiometry,
    SecondCamera,
    SequenceManifest,
)
from workers.pipeline.reconstruction.rgb_method import rgb_prior_poses
from workers.pipeline.synth import RgbOptions, SynthOptions, procedural_block, synthesize

W, H, RW, RH, N = 32, 24, 40, 30, 3
FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _manifest() -> SequenceManifest:
    def recs(prefix: str, ext: str) -> tuple[FrameRecord, ...]:
        return tuple(
            FrameRecord(i, f"{prefix}/{i:06d}.{ext}", 0.5 * i, np.array([691000.0 + i, 5334000.5, 520.3]),
                        np.array([0.4, -1.2, 90.0 + i]))
            for i in range(N)
        )  # fmt: skip

    rgb = SecondCamera(
        camera=Camera(RW, RH, 50.0, 50.0, 19.5, 14.5, k1=-0.05, k2=0.01),
        mounting=Mounting(FORWARD, np.array([0.1, -0.2, 0.3]), np.array([0.4, 0.1, -1.1])),
        frames=recs("rgb", "png"),
        channels=3,
        pose_source="photogrammetric",
        accuracy=Accuracy(np.full(3, 0.01), np.array([0.005, 0.005, 0.01])),
    )
    return SequenceManifest(
        platform="drive", crs="EPSG:25832", camera=Camera(W, H, 40.0, 40.0, 15.5, 11.5),
        radiometry=Radiometry(), mounting=Mounting(FORWARD), frames=recs("frames", "png"), rgb=rgb,
    )  # fmt: skip


def _rgb_frames() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [rng.integers(0, 256, (RH, RW, 3), dtype=np.uint8) for _ in range(N)]


@pytest.fixture()
def package(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    tir = [np.full((H, W), 27315 + i, np.uint16) for i in range(N)]
    rgb = _rgb_frames()
    return write_package(tmp_path / "pkg", _manifest(), tir, rgb), rgb


def test_round_trip(package: tuple[Path, list[np.ndarray]]) -> None:
    root, rgb = package
    want = _manifest().rgb
    with open_package(root) as pkg:
        got = pkg.manifest.rgb
        assert got is not None and pkg.rgb_frames is not None
        assert got.camera == want.camera and got.channels == 3 and got.pose_source == "photogrammetric"
        assert np.allclose(got.mounting.camera_to_body, FORWARD)
        assert np.allclose(got.mounting.boresight_deg, [0.1, -0.2, 0.3])
        assert np.allclose(got.accuracy.attitude_deg, [0.005, 0.005, 0.01])
        assert [f.file for f in got.frames] == [f.file for f in want.frames]
        assert np.allclose(got.frames[2].attitude_deg, want.frames[2].attitude_deg)
        for i in range(N):  # stored as PNG (B, G, R), read back as R, G, B
            assert np.array_equal(pkg.rgb_frames.load(i), rgb[i])
        assert pkg.frames.load(1).shape == (H, W)


def test_package_without_second_camera_reads_as_before(tmp_path: Path) -> None:
    m = replace(_manifest(), rgb=None)
    root = write_package(tmp_path / "p", m, [np.full((H, W), 30000, np.uint16)] * N)
    assert "rgb_camera" not in json.loads((root / "sequence.json").read_text())
    with open_package(root) as pkg:
        assert pkg.manifest.rgb is None and pkg.rgb_frames is None


def _edit(root: Path, fn: Any) -> None:
    p = root / "sequence.json"
    d = json.loads(p.read_text())
    fn(d["rgb_camera"])
    p.write_text(json.dumps(d))


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda r: r.update(version=2), "rgb_camera.version"),
        (lambda r: r.pop("version"), "rgb_camera.version"),
        (lambda r: r.update(channels=2), "rgb_camera.channels"),
        (lambda r: r.update(pose_source="gps"), "rgb_camera.pose_source"),
        (lambda r: r["camera"].pop("fx"), "rgb_camera.camera.fx"),
        (lambda r: r["camera"].update(fy=-1.0), "rgb_camera.camera.fy"),
        (lambda r: r["mounting"].update(camera_to_body=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),
         "rgb_camera.mounting.camera_to_body"),
        (lambda r: r["frames"][1].update(time=0.0), "rgb_camera.frames[1].time"),
        (lambda r: r["frames"][2]["position"].__setitem__(1, "x"), "rgb_camera.frames[2].position[1]"),
        (lambda r: r["frames"][0].update(file="../x.png"), "rgb_camera.frames[0].file"),
        (lambda r: r["accuracy"].update(position_m=0), "rgb_camera.accuracy.position_m"),
        (lambda r: r.update(frames=[]), "rgb_camera.frames"),
    ],
)  # fmt: skip
def test_refusals_name_the_field(package: tuple[Path, list[np.ndarray]], edit: Any, field: str) -> None:
    root, _ = package
    _edit(root, edit)
    with pytest.raises(PackageError) as err:
        open_package(root)
    assert err.value.field == field
    assert str(err.value).startswith(field)


def test_refusals_name_the_file(package: tuple[Path, list[np.ndarray]]) -> None:
    root, _ = package
    cv2.imwrite(str(root / "rgb/000001.png"), np.zeros((RH, RW + 1, 3), np.uint8))
    with pytest.raises(PackageError, match=r"^rgb/000001.png: frame size 41x30 differs"):
        open_package(root)
    cv2.imwrite(str(root / "rgb/000001.png"), np.zeros((RH, RW), np.uint8))
    with pytest.raises(PackageError, match=r"^rgb/000001.png: expected 3 channel"):
        open_package(root)
    (root / "rgb/000001.png").unlink()
    with pytest.raises(PackageError, match=r"^rgb/000001.png: file not found"):
        open_package(root)


def test_writer_needs_the_rgb_frames(tmp_path: Path) -> None:
    with pytest.raises(PackageError, match=r"^rgb_camera:"):
        write_package(tmp_path / "p", _manifest(), [np.full((H, W), 30000, np.uint16)] * N)


def test_synth_writes_the_rgb_camera(tmp_path: Path) -> None:
    rgb_o = RgbOptions(width=96, height=80)
    res = synthesize(procedural_block(6, seed=2), SynthOptions(n_frames=3, seed=2, buildings=2, rgb=rgb_o))
    assert res.rgb is not None and res.manifest.rgb is not None
    # the manifest's positions / attitudes give back the recorded RGB poses (and they are near the truth)
    recorded = rgb_prior_poses(res.manifest, None)
    for got, want, true in zip(recorded, res.rgb.recorded_poses, res.rgb.true_poses, strict=True):
        assert np.allclose(got.center, want.center, atol=1e-6)
        assert np.allclose(got.R_world_from_cam, want.R_world_from_cam, atol=1e-9)
        assert np.linalg.norm(got.center - true.center) < 0.05
    # the RGB camera sits where the options put it relative to the true TIR camera
    off = res.truth.poses[0].cam_from_world(res.rgb.true_poses[0].center[None])[0]
    assert np.allclose(off, rgb_o.offset_m, atol=1e-9)
    root = write_synthetic_package(res, tmp_path / "seq")
    with open_package(root) as pkg:
        img = pkg.rgb_frames.load(1)
        assert img.shape == (80, 96, 3) and img.dtype == np.uint8
        assert np.array_equal(img, res.rgb.frames[1])
        assert img.std() > 5  # textured, not blank


def test_cli_synth_rgb(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from services.cli import app

    out = tmp_path / "pkg"
    args = ["synth", "-o", str(out), "--procedural", "6", "--buildings", "2", "--frames", "2", "--rgb",
            "--rgb-width", "160", "--rgb-height", "128", "--supersample", "1"]  # fmt: skip
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    with open_package(out) as pkg:
        assert pkg.manifest.rgb is not None and pkg.manifest.rgb.pose_source == "photogrammetric"
        assert pkg.rgb_frames.load(1).shape == (128, 160, 3)


def test_the_docs_example_parses() -> None:
    from db.sequence_rgb import parse_rgb_camera

    md = (Path(__file__).resolve().parents[2] / "docs" / "sequence-format.md").read_text()
    start = md.index('```json\n{\n  "rgb_camera"') + len("```json\n")
    rgb = parse_rgb_camera(json.loads(md[start : md.index("```", start)])["rgb_camera"])
    assert rgb.camera.width == 1280 and rgb.pose_source == "photogrammetric" and rgb.channels == 3
    assert rgb.frames[0].file == "rgb/000000.png"
