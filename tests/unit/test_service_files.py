"""Pure pieces of the service's workers: storage names and atomic files, the results the units
keep for the finish, the Celery settings, and `ingest_buildings` (the ingest body `citytherm run`
and the service share)."""

from __future__ import annotations

import pickle
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from db.citygml.reader import read_header, read_model
from db.results_folder.write import read_tile, write_tile
from db.settings import Settings
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, look_at
from workers import service_results
from workers.celery_app import celery_config, grace_s, stale_after_s
from workers.job import RunError, RunOptions, ingest, ingest_buildings
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.results import TextureTile
from workers.service_storage import (
    read_pickle,
    safe_name,
    unit_path,
    write_atomic,
    write_pickle,
    write_pickles,
    zip_folder,
)


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


def test_pickles_written_together_are_each_whole_and_an_error_is_raised(tmp_path: Path) -> None:
    items = [(tmp_path / "units" / f"u{k}.pkl", {"k": k, "a": np.arange(k)}) for k in range(20)]
    write_pickles(items, threads=4)
    for path, obj in items:
        got = read_pickle(path)
        assert got["k"] == obj["k"] and np.array_equal(got["a"], obj["a"])
    assert sorted(p.name for p in (tmp_path / "units").iterdir()) == sorted(p.name for p, _ in items)
    with pytest.raises((pickle.PicklingError, AttributeError)):  # a local function cannot be pickled
        write_pickles([(tmp_path / "bad.pkl", lambda: 0), (tmp_path / "good.pkl", 1)])
    assert not (tmp_path / "bad.pkl").exists()


@dataclass(frozen=True, eq=False)
class _Result:
    """The fields of a `BuildingResult` the kept results use."""

    building_id: str
    tiles: tuple[TextureTile, ...]


def test_a_kept_result_gives_the_tiles_write_tile_writes_and_the_result_without_pixels(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(service_results, "job_dir", lambda job_id: tmp_path / "jobs" / str(job_id))
    jid = uuid.uuid4()
    rng = np.random.default_rng(3)
    tiles = tuple(TextureTile(f"textures/a:b_{k}.png", rng.integers(0, 65535, (9, 7), dtype=np.uint16))
                  for k in range(2))  # fmt: skip
    assert service_results.keep_result(jid, _Result("a:b", tiles))  # type: ignore[arg-type]
    want = tmp_path / "want"
    for t in tiles:
        write_tile(want, t)
    out = tmp_path / "out"
    got = service_results.kept_result(jid, "a:b", out)
    assert got is not None and got.building_id == "a:b"
    assert [t.name for t in got.tiles] == [t.name for t in tiles] and all(t.dn.size == 0 for t in got.tiles)
    for t in tiles:  # the same files as written in the finish
        assert (out / t.name).read_bytes() == (want / t.name).read_bytes()
        assert np.array_equal(read_tile(out, t.name).dn, t.dn)
    # nothing kept: the finish reads PostGIS
    assert service_results.kept_result(jid, "other", tmp_path / "out2") is None
    # a kept result whose tiles are gone is not used, and leaves nothing in the results folder
    (service_results.kept_dir(jid) / tiles[1].name).unlink()
    out3 = tmp_path / "out3"
    assert service_results.kept_result(jid, "a:b", out3) is None
    assert not any(p.is_file() for p in out3.rglob("*"))


def test_keeping_a_result_that_cannot_be_written_leaves_no_pickle(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(service_results, "job_dir", lambda job_id: tmp_path / "jobs" / str(job_id))
    jid = uuid.uuid4()
    bad = TextureTile("textures/b_0.png", np.zeros((0, 5), np.uint16))  # an empty image: no PNG
    assert not service_results.keep_result(jid, _Result("b", (bad,)))  # type: ignore[arg-type]
    assert service_results.kept_result(jid, "b", tmp_path / "out") is None


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
