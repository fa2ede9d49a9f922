"""Frames decoded ahead while a job calibrates (`workers.service_frames`), with the job's row
replaced by a stand-in: what the prefetch decodes into the process's frame cache, and when it
does nothing or stops."""

from __future__ import annotations

import uuid
from pathlib import Path

import numpy as np
import pytest

from db import sequence_package
from db.sequence_package import open_package
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, look_at
from workers import service_frames as sf
from workers.pipeline.geometry.camera import Camera

CAM = Camera(96, 80, 90.0, 90.0, 47.5, 39.5)


@pytest.fixture
def package(tmp_path: Path) -> Path:
    poses = [look_at([-3 + 1.0 * k, -15, 1.6], [0 + 1.0 * k, 0, 3.5]) for k in range(20)]
    _, pkg = write_scene(tmp_path, [box_building("B1", 0, 0, 12, 8, 7)], CAM, poses)
    return pkg


def cached_files(pkg: Path) -> set[str]:
    """The package's frame files in this process's frame cache (decoded stored values)."""
    root = str(open_package(pkg).root / "frames")
    return {Path(k[0]).name for k in sequence_package._FRAMES if str(k[0]).startswith(root)}


@pytest.fixture
def job(package: Path, monkeypatch: pytest.MonkeyPatch) -> dict:
    """The stand-in job row (`status`, `stage`, `looks`: how often the prefetch looked at it)."""
    row = {"status": "running", "stage": "calibrate", "looks": 0}

    def look(job_id: uuid.UUID) -> tuple[str, str, str]:
        row["looks"] += 1
        return row["status"], row["stage"], str(package)

    monkeypatch.setattr(sf, "_job", look)
    monkeypatch.setattr(sequence_package, "_FRAMES", type(sequence_package._FRAMES)())
    monkeypatch.setattr(sequence_package, "_CACHED_BYTES", [0])
    return row


def test_a_calibrating_job_gets_every_frame_decoded_as_the_stages_load_it(package: Path, job: dict) -> None:
    assert sf.prefetch_frames(str(uuid.uuid4())) == "decoded 20 frames"
    assert cached_files(package) == {f"{i:06d}.png" for i in range(20)}
    with open_package(package) as pkg:  # what a window or unit loads is the cached frame
        fresh = sequence_package.physical_from_raw(
            sequence_package.read_frame_raw(pkg.root / pkg.frames.files[3], "f"), pkg.manifest.radiometry
        )
        np.testing.assert_array_equal(pkg.frames.load(3), fresh)
    assert job["looks"] == 1 + (20 - 1) // sf.CHECK_EVERY


@pytest.mark.parametrize(
    ("status", "stage"), [("running", "orient"), ("running", "units"), ("dismissed", "calibrate")]
)
def test_a_job_past_calibrating_or_final_gets_nothing_decoded(
    package: Path, job: dict, status: str, stage: str
) -> None:
    job.update(status=status, stage=stage)
    assert sf.prefetch_frames(str(uuid.uuid4())) == "late"
    assert cached_files(package) == set()


def test_the_prefetch_stops_when_the_job_moves_on_to_orient(
    package: Path, job: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    looks = {"n": 0}

    def calibrating(job_id: uuid.UUID) -> bool:  # the calibration ends after the first look
        looks["n"] += 1
        return looks["n"] < 2

    monkeypatch.setattr(sf, "_calibrating", calibrating)
    assert sf.prefetch_frames(str(uuid.uuid4())) == f"decoded {2 * sf.CHECK_EVERY} frames"
    assert len(cached_files(package)) == 2 * sf.CHECK_EVERY


def test_the_prefetch_stops_when_the_frame_cache_is_full(
    package: Path, job: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    per_frame = CAM.width * CAM.height * 2  # uint16 as stored (the cache keeps no physical values)
    monkeypatch.setattr(sf, "FRAME_CACHE_BYTES", 5 * per_frame)
    assert sf.prefetch_frames(str(uuid.uuid4())) == "decoded 5 frames"


def test_a_failing_prefetch_is_logged_and_never_raises(job: dict, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(sf, "_job", lambda job_id: ("running", "calibrate", str(tmp_path / "gone")))
    assert sf.prefetch_frames(str(uuid.uuid4())) == "not a folder"
    (tmp_path / "broken").mkdir()
    monkeypatch.setattr(sf, "_job", lambda job_id: ("running", "calibrate", str(tmp_path / "broken")))
    assert sf.prefetch_frames(str(uuid.uuid4())) == "failed"
