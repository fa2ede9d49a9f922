"""Sequence package reader and writer: containers, frame types, every refusal of the spec."""

from __future__ import annotations

import io
import json
import pickle
import stat
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import tifffile

from db.sequence_package import (
    PackageError,
    SequencePackage,
    manifest_to_dict,
    open_package,
    write_package,
)
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import (
    Accuracy,
    FrameRecord,
    GroundControl,
    ImuSamples,
    Mounting,
    Radiometry,
    SequenceManifest,
)

W, H = 32, 24
CAM = Camera(W, H, 40.0, 40.0, 15.5, 11.5, k1=-0.12, k2=0.05)
FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
N = 3


def make_manifest(files: list[str] | None = None) -> SequenceManifest:
    files = files or [f"frames/{i:06d}.png" for i in range(N)]
    frames = tuple(
        FrameRecord(
            i, f, 0.5 * i, np.array([691000.0 + i, 5334000.5, 520.3]), np.array([0.4, -1.2, 359.0 + i])
        )
        for i, f in enumerate(files)
    )
    t = np.arange(0.0, 1.001, 0.05)
    imu = ImuSamples(
        t,
        np.column_stack([691000 + 2 * t, np.full_like(t, 5334000.5), np.full_like(t, 520.3)]),
        np.column_stack([np.full_like(t, 0.4), np.full_like(t, -1.2), (359.0 + 2 * t) % 360]),
    )
    gcps = GroundControl(
        {
            "G1": (np.array([691010.0, 5334020.0, 500.0]), 0.01),
            "G2": (np.array([691011.0, 5334021.0, 501.0]), None),
        },
        ((0, "G1", np.array([10.5, 7.25])), (2, "G2", np.array([3.0, 4.0]))),
    )
    return SequenceManifest(
        platform="drive",
        crs="EPSG:25832",
        camera=CAM,
        radiometry=Radiometry("K", 0.01, 0.0),
        mounting=Mounting(FORWARD, np.array([0.1, -0.2, 0.3]), np.array([1.0, 0.0, -0.5])),
        frames=frames,
        accuracy=Accuracy(np.array([2.0, 2.0, 3.0]), np.array([0.5, 0.5, 1.0])),
        imu=imu,
        gcps=gcps,
    )


def dn_frames(n: int = N) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    frames = [rng.integers(27000, 31000, (H, W)).astype(np.uint16) for _ in range(n)]
    frames[0][0, 0] = 0  # not observed
    return frames


@pytest.fixture()
def package_dir(tmp_path: Path) -> Path:
    return write_package(tmp_path / "pkg", make_manifest(), dn_frames())


def edit(pkg: Path, change: Callable[[dict], None]) -> Path:
    d = json.loads((pkg / "sequence.json").read_text())
    change(d)
    (pkg / "sequence.json").write_text(json.dumps(d))
    return pkg


def refused(path: Path, **kw) -> PackageError:
    with pytest.raises(PackageError) as exc:
        open_package(path, **kw)
    err = exc.value
    assert isinstance(err, ValueError)
    assert err.field in str(err)  # the message names the field or file
    return err


def check_package(pkg: SequencePackage) -> None:
    m = pkg.manifest
    ref = make_manifest()
    assert len(m.frames) == N and m.crs == "EPSG:25832" and m.camera == CAM
    np.testing.assert_array_equal(m.frames[2].position, ref.frames[2].position)
    np.testing.assert_array_equal(m.mounting.lever_arm_m, [1.0, 0.0, -0.5])
    np.testing.assert_array_equal(m.imu.attitude_deg, ref.imu.attitude_deg)
    assert m.gcps.points["G2"][1] is None and m.gcps.observations[0][1] == "G1"
    np.testing.assert_array_equal(m.accuracy.position_m, [2.0, 2.0, 3.0])
    frames = dn_frames()
    img = pkg.frames.load(1)
    assert img.dtype == np.float32 and img.shape == (H, W)
    np.testing.assert_allclose(img, frames[1] * 0.01, rtol=1e-6)
    first = pkg.frames.load(0)
    assert np.isnan(first[0, 0]) and np.isfinite(first[0, 1:]).all()
    # picklable frame source: loads the same values in another process
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(pkg.frames)).load(1), img)


# -- valid packages -------------------------------------------------------------------------------
def test_directory_package(package_dir: Path) -> None:
    with open_package(package_dir) as pkg:
        check_package(pkg)
        assert pkg.root == package_dir
    with open_package(package_dir / "sequence.json") as pkg:
        check_package(pkg)


def zip_dir(src: Path, out: Path, prefix: str = "") -> Path:
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(src.rglob("*")):
            zf.write(f, prefix + f.relative_to(src).as_posix())
    return out


@pytest.mark.parametrize("kind", ["zip", "zip-folder", "tar", "tar.gz"])
def test_archive_packages(package_dir: Path, tmp_path: Path, kind: str) -> None:
    if kind.startswith("zip"):
        arc = zip_dir(package_dir, tmp_path / "seq.zip", "seq/" if kind == "zip-folder" else "")
    else:
        arc = tmp_path / f"seq.{kind}"
        with tarfile.open(arc, "w:gz" if kind == "tar.gz" else "w") as tf:
            tf.add(package_dir, arcname=".")
    pkg = open_package(arc)
    check_package(pkg)
    root = pkg.root
    assert root.is_dir() and not root.is_relative_to(tmp_path)
    pkg.close()
    assert not root.exists()  # the temporary extraction is gone


def test_frame_types_png8_tiff16_tiff32(tmp_path: Path) -> None:
    files = ["f/a.png", "f/b.tif", "f/c.tiff"]
    m = make_manifest(files)
    dn = dn_frames()
    vals = dn[2].astype(np.float32) * 0.5
    write_package(tmp_path, m, [(dn[0] // 256).astype(np.uint8), dn[1], vals])
    assert tifffile.imread(tmp_path / "f/c.tiff").dtype == np.float32
    with open_package(tmp_path) as pkg:
        np.testing.assert_array_equal(pkg.frames.load(0), dn[0] // 256)  # 8-bit: display values
        np.testing.assert_allclose(pkg.frames.load(1)[1:], dn[1][1:] * 0.01, rtol=1e-6)
        np.testing.assert_allclose(pkg.frames.load(2), vals * 0.01, rtol=1e-6)


def test_writer_converts_physical_values_and_round_trips_the_manifest(tmp_path: Path) -> None:
    m = make_manifest()
    temps = [np.full((H, W), 290.0 + i, np.float32) for i in range(N)]
    temps[1][3, 4] = np.nan
    write_package(tmp_path, m, temps)
    with open_package(tmp_path) as pkg:
        np.testing.assert_allclose(pkg.frames.load(2), 292.0, atol=0.006)
        assert np.isnan(pkg.frames.load(1)[3, 4])
        assert manifest_to_dict(pkg.manifest) == manifest_to_dict(m)
    d = json.loads((tmp_path / "sequence.json").read_text())
    assert d["format"] == "citytherm-sequence/1" and d["imu"] == "imu.csv" and d["gcps"] == "gcps.json"
    assert (tmp_path / "imu.csv").read_text().splitlines()[0] == "time,x,y,z,roll,pitch,heading"


def test_writer_refuses_wrong_frame_count_and_size(tmp_path: Path) -> None:
    with pytest.raises(PackageError, match="2 images"):
        write_package(tmp_path / "a", make_manifest(), dn_frames(2))
    with pytest.raises(PackageError, match="4 images"):
        write_package(tmp_path / "b", make_manifest(), dn_frames(4))
    with pytest.raises(PackageError, match=r"frames/000000\.png"):
        write_package(tmp_path / "c", make_manifest(), [np.zeros((H + 1, W), np.uint16)] * N)


# -- the spec's refusals --------------------------------------------------------------------------
def test_refuses_unknown_format(package_dir: Path) -> None:
    err = refused(edit(package_dir, lambda d: d.update(format="citytherm-sequence/2")))
    assert err.field == "format" and "citytherm-sequence/2" in str(err)


def test_refuses_missing_frame(package_dir: Path) -> None:
    (package_dir / "frames/000001.png").unlink()
    assert refused(package_dir).field == "frames/000001.png"


def test_refuses_unreadable_frame(package_dir: Path) -> None:
    (package_dir / "frames/000002.png").write_bytes(b"\x89PNG garbage")
    assert refused(package_dir).field == "frames/000002.png"
    # also found lazily when the header check is skipped
    with open_package(package_dir, check_frames=False) as pkg, pytest.raises(PackageError) as exc:
        pkg.frames.load(2)
    assert exc.value.field == "frames/000002.png"


def test_refuses_wrong_frame_size(package_dir: Path) -> None:
    import cv2

    cv2.imwrite(str(package_dir / "frames/000001.png"), np.ones((H, W + 1), np.uint16))
    err = refused(package_dir)
    assert err.field == "frames/000001.png" and f"{W + 1}x{H}" in str(err)
    with open_package(package_dir, check_frames=False) as pkg, pytest.raises(PackageError, match="000001"):
        pkg.frames.load(1)


def test_refuses_multichannel_frame(package_dir: Path) -> None:
    import cv2

    cv2.imwrite(str(package_dir / "frames/000000.png"), np.ones((H, W, 3), np.uint8))
    assert refused(package_dir).field == "frames/000000.png"


@pytest.mark.parametrize(
    "path, value, field",
    [
        (("frames", 1, "position", 1), float("nan"), "frames[1].position[1]"),
        (("frames", 0, "attitude_deg", 2), float("inf"), "frames[0].attitude_deg[2]"),
        (("camera", "fx"), float("-inf"), "camera.fx"),
        (("camera", "k1"), "0.1", "camera.k1"),
        (("vertical_offset_m",), float("nan"), "vertical_offset_m"),
        (("mounting", "lever_arm_m", 0), None, "mounting.lever_arm_m[0]"),
    ],
)
def test_refuses_non_finite_numbers(package_dir: Path, path: tuple, value: object, field: str) -> None:
    def change(d: dict) -> None:
        target = d
        for k in path[:-1]:
            target = target[k]
        target[path[-1]] = value

    assert refused(edit(package_dir, change)).field == field


@pytest.mark.parametrize(
    "path, field",
    [
        (("frames", 0, "time"), "frames[0].time"),
        (("frames", 2, "position"), "frames[2].position"),
        (("camera", "cy"), "camera.cy"),
        (("radiometry", "scale"), "radiometry.scale"),
        (("mounting", "boresight_deg"), "mounting.boresight_deg"),
        (("crs",), "crs"),
    ],
)
def test_refuses_missing_numbers_and_fields(package_dir: Path, path: tuple, field: str) -> None:
    def change(d: dict) -> None:
        target = d
        for k in path[:-1]:
            target = target[k]
        del target[path[-1]]

    err = refused(edit(package_dir, change))
    assert err.field == field and "missing" in str(err)


def test_refuses_short_vector(package_dir: Path) -> None:
    err = refused(edit(package_dir, lambda d: d["frames"][1].update(position=[1.0, 2.0])))
    assert err.field == "frames[1].position"


@pytest.mark.parametrize(
    "M",
    [
        [[0, 0, 1.01], [1, 0, 0], [0, 1, 0]],  # scaled
        [[0, 0, 1], [1, 0, 0], [0, -1, 0]],  # reflection: det = -1
        [[0, 0, 1], [1, 0, 0], [0, 1, 0.00001]],  # slightly skewed
    ],
)
def test_refuses_non_orthonormal_mounting(package_dir: Path, M: list) -> None:
    err = refused(edit(package_dir, lambda d: d["mounting"].update(camera_to_body=M)))
    assert err.field == "mounting.camera_to_body" and "det" in str(err)


def test_accepts_orthonormal_mounting_to_1e_7(package_dir: Path) -> None:
    M = (FORWARD * (1 + 1e-8)).tolist()
    with open_package(edit(package_dir, lambda d: d["mounting"].update(camera_to_body=M))) as pkg:
        assert pkg.manifest.mounting.camera_to_body[0, 2] == pytest.approx(1.0)


@pytest.mark.parametrize("t2", [0.5, 0.2])
def test_refuses_times_not_increasing(package_dir: Path, t2: float) -> None:
    err = refused(edit(package_dir, lambda d: d["frames"][2].update(time=t2)))
    assert err.field == "frames[2].time"


def test_refuses_imu_problems(package_dir: Path) -> None:
    lines = (package_dir / "imu.csv").read_text().splitlines()
    (package_dir / "imu.csv").write_text("\n".join([*lines[:3], lines[2], *lines[3:]]) + "\n")
    assert refused(package_dir).field == "imu.csv:4.time"  # the repeated line
    (package_dir / "imu.csv").write_text("t,x,y,z,roll,pitch,heading\n0,1,2,3,4,5,6\n")
    assert refused(package_dir).field == "imu.csv"
    (package_dir / "imu.csv").write_text("time,x,y,z,roll,pitch,heading\n0,1,2,3,4,5,nan\n")
    assert refused(package_dir).field == "imu.csv:2.heading"
    (package_dir / "imu.csv").unlink()
    assert refused(package_dir).field == "imu.csv"


def test_refuses_gcp_problems(package_dir: Path) -> None:
    g = json.loads((package_dir / "gcps.json").read_text())
    g["observations"][0]["id"] = "G9"
    (package_dir / "gcps.json").write_text(json.dumps(g))
    err = refused(package_dir)
    assert err.field == "gcps.json.observations[0].id" and "G9" in str(err)
    g["observations"][0].update(id="G1", frame=N)
    (package_dir / "gcps.json").write_text(json.dumps(g))
    assert refused(package_dir).field == "gcps.json.observations[0].frame"


@pytest.mark.parametrize("crs", ["EPSG:999999", "urn:adv:crs:ETRS89_UTM99", "not a crs"])
def test_refuses_unknown_crs(package_dir: Path, crs: str) -> None:
    err = refused(edit(package_dir, lambda d: d.update(crs=crs)))
    assert err.field == "crs" and crs in str(err)


def test_accepts_crs_spellings(package_dir: Path) -> None:
    for crs in ("model", "EPSG:4979", "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016"):
        with open_package(edit(package_dir, lambda d, c=crs: d.update(crs=c))) as pkg:
            assert pkg.manifest.crs == crs


@pytest.mark.parametrize(
    "field, value",
    [
        ("platform", "boat"),
        ("radiometry", {"unit": "F", "scale": 1, "offset": 0}),
        ("attitude", "grid"),
        ("attitude", {"heading_reference": "magnetic"}),
        ("camera", {"model": "FISHEYE"}),
        ("accuracy", {"position_m": -1, "attitude_deg": 0.5}),
        ("frames", []),
    ],
)
def test_refuses_bad_choices(package_dir: Path, field: str, value: object) -> None:
    err = refused(edit(package_dir, lambda d: d.update({field: value})))
    assert err.field.startswith(field)


def test_refuses_frame_path_escaping_the_package(package_dir: Path) -> None:
    err = refused(edit(package_dir, lambda d: d["frames"][0].update(file="../outside.png")))
    assert err.field == "frames[0].file"
    err = refused(edit(package_dir, lambda d: d["frames"][0].update(file="/etc/passwd")))
    assert err.field == "frames[0].file"


def test_refuses_bad_json_and_missing_manifest(package_dir: Path, tmp_path: Path) -> None:
    (package_dir / "sequence.json").write_text("{not json")
    assert refused(package_dir).field == "sequence.json"
    (package_dir / "sequence.json").unlink()
    assert refused(package_dir).field == "sequence.json"
    (tmp_path / "x.bin").write_bytes(b"plain bytes")
    assert refused(tmp_path / "x.bin").field == "x.bin"


# -- hostile archives -----------------------------------------------------------------------------
def zip_with(tmp_path: Path, package_dir: Path, extra: zipfile.ZipInfo, data: bytes = b"x") -> Path:
    arc = zip_dir(package_dir, tmp_path / "hostile.zip")
    with zipfile.ZipFile(arc, "a") as zf:
        zf.writestr(extra, data)
    return arc


def tar_with(tmp_path: Path, package_dir: Path, extra: tarfile.TarInfo, data: bytes = b"") -> Path:
    arc = tmp_path / "hostile.tar.gz"
    with tarfile.open(arc, "w:gz") as tf:
        tf.add(package_dir, arcname=".")
        tf.addfile(extra, io.BytesIO(data) if data else None)
    return arc


@pytest.mark.parametrize("name", ["../evil.txt", "frames/../../evil.txt", "/tmp/evil.txt", "C:/evil.txt"])
def test_refuses_zip_slip(package_dir: Path, tmp_path: Path, name: str) -> None:
    arc = zip_with(tmp_path, package_dir, zipfile.ZipInfo(name))
    assert refused(arc).field == name
    assert not (tmp_path / "evil.txt").exists()


def test_refuses_tar_slip(package_dir: Path, tmp_path: Path) -> None:
    info = tarfile.TarInfo("../evil.txt")
    info.size = 1
    assert refused(tar_with(tmp_path, package_dir, info, b"x")).field == "../evil.txt"


def test_refuses_symlink_members(package_dir: Path, tmp_path: Path) -> None:
    zi = zipfile.ZipInfo("frames/link.png")
    zi.external_attr = (stat.S_IFLNK | 0o777) << 16
    err = refused(zip_with(tmp_path, package_dir, zi, b"/etc/passwd"))
    assert err.field == "frames/link.png" and "link" in str(err)
    ti = tarfile.TarInfo("frames/link.png")
    ti.type, ti.linkname = tarfile.SYMTYPE, "/etc/passwd"
    assert refused(tar_with(tmp_path, package_dir, ti)).field == "frames/link.png"
    ti = tarfile.TarInfo("frames/hard.png")
    ti.type, ti.linkname = tarfile.LNKTYPE, "sequence.json"
    assert refused(tar_with(tmp_path, package_dir, ti)).field == "frames/hard.png"


def test_refuses_device_members(package_dir: Path, tmp_path: Path) -> None:
    ti = tarfile.TarInfo("dev/null")
    ti.type = tarfile.CHRTYPE
    err = refused(tar_with(tmp_path, package_dir, ti))
    assert err.field == "dev/null" and "devices" in str(err)
    ti = tarfile.TarInfo("fifo")
    ti.type = tarfile.FIFOTYPE
    assert refused(tar_with(tmp_path, package_dir, ti)).field == "fifo"


def test_refuses_archive_past_size_limit(package_dir: Path, tmp_path: Path) -> None:
    # a highly compressible member: 5 MB of zeros, a few kB compressed
    zi = zipfile.ZipInfo("padding.bin")
    zi.compress_type = zipfile.ZIP_DEFLATED
    arc = zip_with(tmp_path, package_dir, zi, bytes(5_000_000))
    assert arc.stat().st_size < 100_000
    err = refused(arc, max_bytes=1_000_000)
    assert "limit" in str(err) and "1000000" in str(err)
    with open_package(arc, max_bytes=10_000_000) as pkg:  # the same archive within the limit
        assert len(pkg.manifest.frames) == N
    tgz = tmp_path / "big.tar.gz"
    with tarfile.open(tgz, "w:gz") as tf:
        tf.add(package_dir, arcname=".")
        ti = tarfile.TarInfo("padding.bin")
        ti.size = 5_000_000
        tf.addfile(ti, io.BytesIO(bytes(5_000_000)))
    assert "limit" in str(refused(tgz, max_bytes=1_000_000))


def test_refuses_too_many_members(package_dir: Path, tmp_path: Path) -> None:
    arc = zip_dir(package_dir, tmp_path / "seq.zip")
    err = refused(arc, max_members=3)
    assert "members" in str(err)
    tgz = tmp_path / "seq.tar"
    with tarfile.open(tgz, "w") as tf:
        tf.add(package_dir, arcname=".")
    assert "members" in str(refused(tgz, max_members=3))


def test_refuses_encrypted_or_corrupt_archives(package_dir: Path, tmp_path: Path) -> None:
    arc = zip_dir(package_dir, tmp_path / "seq.zip")
    data = bytearray(arc.read_bytes())
    i = data.find(b"sequence.json") + len(b"sequence.json") + 20  # inside the manifest's data
    data[i : i + 40] = bytes(40)
    bad = tmp_path / "bad.zip"
    bad.write_bytes(bytes(data))
    assert refused(bad).field in ("bad.zip", "sequence.json")


def test_directory_package_symlink_out_is_refused(package_dir: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside.png"
    (package_dir / "frames/000001.png").rename(outside)
    (package_dir / "frames/000001.png").symlink_to(outside)
    err = refused(package_dir)
    assert err.field == "frames/000001.png" and "outside" in str(err)


def _json_blocks(md: Path) -> list[dict]:
    import re

    blocks = re.findall(r"```json\n(.*?)```", md.read_text(encoding="utf-8"), flags=re.S)
    return [json.loads(b) for b in blocks]


def test_the_docs_example_parses() -> None:
    """The manifest example of the repository's sequence format page parses as written."""
    from db.sequence_manifest import parse_manifest

    md = Path(__file__).resolve().parents[2] / "docs" / "sequence-format.md"
    examples = [d for d in _json_blocks(md) if d.get("format") == "citytherm-sequence/1"]
    assert examples, md
    for d in examples:
        m = parse_manifest(d)  # no root: files are not touched
        assert m.camera.width == 640 and m.frames[0].attitude_deg[2] == 87.0, md
        assert m.mounting.camera_to_body[0, 2] == 1.0 and m.heading_reference == "grid"
