"""Pure pieces of the service's workers: storage names and atomic files, the Celery settings,
and `ingest_buildings` (the ingest body `citytherm run` and the service share)."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import pytest

from db.citygml.reader import read_header, read_model
from db.settings import Settings
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, look_at
from workers.celery_app import celery_config, grace_s, stale_after_s
from workers.job import RunError, RunOptions, ingest, ingest_buildings
from workers.pipeline.geometry.camera import Camera
from workers.service_storage import read_pickle, safe_name, unit_path, write_atomic, write_pickle, zip_folder


def test_safe_names_are_file_names_and_never_shared() -> None:
    ids = ["BLDG_0001", "a/b", "a_b", "a:b", "../x", ".hidden", "é", "x" * 300, "DEB_LOD2_UUID_9e-a.1"]
    names = [safe_name(i) for i in ids]
    assert len(set(names)) == len(ids)
    assert (
        safe_name("BLDG_0001") == "BLDG_0001" and safe_name("DEB_LOD2_UUID_9e-a.1") == "DEB_LOD2_UUID_9e-a.1"
    )
    for n in names:
        assert "/" not in n and not n.startswith(".") and 0 < len(n) <= 120
    assert unit_path("/s", "00000000-0000-0000-0000-000000000001", "a/b").name == f"{safe_name('a/b')}.pkl"


def test_atomic_files_leave_no_temporary_and_replace_whole(tmp_path: Path) -> None:
    path = tmp_path / "jobs" / "j" / "prepared.pkl"
    write_pickle(path, {"a": 1})
    write_pickle(path, {"b": [2, 3]})
    assert read_pickle(path) == {"b": [2, 3]}
    assert [p.name for p in path.parent.iterdir()] == ["prepared.pkl"]
    with pytest.raises(TypeError):
        write_atomic(path, "not bytes")  # type: ignore[arg-type]
    assert pickle.loads(path.read_bytes()) == {"b": [2, 3]}  # the old file stays whole
    assert [p.name for p in path.parent.iterdir()] == ["prepared.pkl"]


def test_the_results_zip_holds_every_file_by_its_relative_name(tmp_path: Path) -> None:
    folder = tmp_path / "results"
    (folder / "textures").mkdir(parents=True)
    (folder / "report.json").write_text("{}")
    (folder / "textures" / "B1_0.png").write_bytes(b"png")
    zip_folder(folder, tmp_path / "results.zip")
    with zipfile.ZipFile(tmp_path / "results.zip") as z:
        assert sorted(z.namelist()) == ["report.json", "textures/B1_0.png"]
        assert z.read("textures/B1_0.png") == b"png"


def test_celery_settings_follow_the_design() -> None:
    s = Settings(unit_timeout_s=600.0, sweep_interval_s=15.0, task_max_retries=3, redis_url="redis://h:1/2")
    c = celery_config(s)
    assert c["broker_url"] == "redis://h:1/2"
    assert c["task_acks_late"] and c["task_reject_on_worker_lost"] and c["task_ignore_result"]
    assert c["worker_prefetch_multiplier"] == 1
    unit = c["task_annotations"]["citytherm.run_unit"]
    assert unit["soft_time_limit"] == 600.0 < unit["time_limit"] == 600.0 + grace_s(600.0)
    assert unit["max_retries"] == 3
    longest = max(a["time_limit"] for a in c["task_annotations"].values())
    assert c["broker_transport_options"]["visibility_timeout"] > longest
    assert stale_after_s(600.0) > unit["time_limit"]  # a unit is taken as lost only after its hard limit
    assert c["beat_schedule"]["citytherm-sweep"]["schedule"] == 15.0


def test_ingest_buildings_with_a_source_that_leaves_far_buildings_out_equals_ingest(tmp_path: Path) -> None:
    cam = Camera(240, 192, 220.0, 220.0, 119.5, 95.5)
    buildings = [box_building("B1", 0, 0, 12, 8, 7), box_building("FAR", 2000, 2000, 2005, 2005, 5)]
    poses = [look_at([-3 + 3.0 * k, -15, 1.6], [0 + 3.0 * k, 0, 3.5]) for k in range(4)]
    gml, pkg = write_scene(tmp_path, buildings, cam, poses)
    options = RunOptions.build(refine=False, buildings=("B1",))
    from_file = ingest(gml, pkg, options)
    _, read = read_model(gml)
    near = [b for b in read if b.id != "FAR"]  # as a spatial query would give them
    shared = ingest_buildings(
        read_header(gml), lambda priors, reach: near, pkg, options, city_model="m", model_ids={"B1", "FAR"}
    )
    assert [b.id for b in shared.buildings] == [b.id for b in from_file.buildings] == ["B1"]
    assert shared.n_model_buildings == from_file.n_model_buildings == 2
    assert [p.center.tolist() for p in shared.priors] == [p.center.tolist() for p in from_file.priors]
    with pytest.raises(RunError, match="not in m: NOPE"):
        ingest_buildings(
            read_header(gml),
            lambda p, r: near,
            pkg,
            RunOptions.build(refine=False, buildings=("NOPE",)),
            city_model="m",
            model_ids={"B1", "FAR"},
        )
