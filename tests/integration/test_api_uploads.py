"""The HTTP API's uploads, over HTTP against the real PostGIS test database and Redis (the server
as in `test_api.py`): CityGML models (plain, gzip, refused, storage full), chunked sequence
uploads with checksums, gaps and limits, a package with a missing frame, registration by path, and
the removal of abandoned uploads."""

from __future__ import annotations

import gzip
import os
import shutil
import time
import uuid
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from tests.integration.conftest import (
    MAX_UPLOAD,
    ApiServer,
    assert_problem,
    content_md5,
    package_variant,
    tar_gz,
    upload_parts,
)
from workers.pipeline.synth import BUNDLED_MODEL

pytestmark = pytest.mark.integration


# -- city models -------------------------------------------------------------------------------
def _post_model(c: httpx.Client, name: str, body: object, mime: str = "application/xml", gz: bool = False):
    headers = {"Content-Type": mime, **({"Content-Encoding": "gzip"} if gz else {})}
    return c.post("/models", params={"name": name}, content=body, headers=headers)


def test_model_upload_plain_and_gzip(api: ApiServer, db_engine) -> None:
    data = BUNDLED_MODEL.read_bytes()
    with api.client("submit") as c:
        r = _post_model(c, "api-up", data, "application/gml+xml")
        assert r.status_code == 202, r.text
        mid = r.json()["id"]
        assert r.json()["status"] == "importing" and r.headers["location"] == f"/models/{mid}"
        assert (api.storage / "uploads" / "models" / f"{mid}.gml").read_bytes() == data
        view = c.get(f"/models/{mid}").json()
        assert view["name"] == "api-up" and view["status"] in ("importing", "ready")
        assert mid in [m["id"] for m in c.get("/models").json()["models"]]
        assert_problem(_post_model(c, "api-up", data), 409)
        r = _post_model(c, "api-up-gz", gzip.compress(data), gz=True)
        assert r.status_code == 202, r.text
        assert (api.storage / "uploads" / "models" / f"{r.json()['id']}.gml").read_bytes() == data
    with db_engine.connect() as conn:
        rows = conn.execute(
            text("SELECT name, status, bytes FROM model_import WHERE name LIKE 'api-up%' ORDER BY name")
        ).all()
    assert [tuple(r) for r in rows] == [
        ("api-up", "importing", len(data)),
        ("api-up-gz", "importing", len(data)),
    ]


def test_model_upload_refused(api: ApiServer, db_engine) -> None:
    uploads = api.storage / "uploads" / "models"
    before = sorted(uploads.glob("*"))
    big = BUNDLED_MODEL.read_bytes() + b"<!--" + b"x" * MAX_UPLOAD + b"-->"
    with api.client("submit") as c:
        assert "CityGML" in assert_problem(_post_model(c, "bad1", b"no xml"), 400)["detail"]
        html = b"<?xml version='1.0'?><html><body/></html>"
        assert "root element" in assert_problem(_post_model(c, "bad2", html), 400)["detail"]
        assert_problem(_post_model(c, "bad3", gzip.compress(BUNDLED_MODEL.read_bytes())[:5000], gz=True), 400)
        assert_problem(_post_model(c, "bad4", b"<a/>", "text/plain"), 415)
        assert_problem(_post_model(c, "big1", big), 413)
        chunks = (big[i : i + 65536] for i in range(0, len(big), 65536))  # no Content-Length: counted
        assert_problem(_post_model(c, "big2", chunks), 413)
        bomb = gzip.compress(big)  # small compressed, too large decoded
        assert len(bomb) < MAX_UPLOAD
        assert_problem(_post_model(c, "big3", bomb, gz=True), 413)
    # nothing of the refused uploads is left (an earlier test's import may remove its own file)
    assert set(uploads.glob("*")) <= set(before)
    with db_engine.connect() as conn:
        n = conn.execute(text("SELECT count(*) FROM model_import WHERE name LIKE 'bad%' OR name LIKE 'big%'"))
        assert n.scalar_one() == 0


def test_upload_refused_when_storage_is_full(make_api) -> None:
    full = make_api(min_free_bytes=10**18)
    with full.client("submit") as c:
        assert "free" in assert_problem(_post_model(c, "full", b"<a/>"), 507)["detail"]
        sid = c.post("/sequences").json()["id"]
        assert_problem(c.put(f"/sequences/{sid}/parts/1", content=b"abc"), 507)
    assert not any((full.storage / "uploads").rglob("*.tmp*"))


# -- sequences ---------------------------------------------------------------------------------
def test_sequence_chunked_upload_and_commit(api: ApiServer, synth_package: Path) -> None:
    data = tar_gz(synth_package)
    with api.client("submit") as c:
        sid = upload_parts(c, data, parts=3)
        again = data[: -(-len(data) // 3)]
        r = c.put(f"/sequences/{sid}/parts/1", content=again, headers={"Content-MD5": content_md5(again)})
        assert r.status_code == 200 and r.json()["bytes"] == len(data)  # replaced, not added
        view = c.get(f"/sequences/{sid}").json()
        assert view["status"] == "open" and [p["n"] for p in view["parts"]] == [1, 2, 3]
        r = c.post(f"/sequences/{sid}/commit")
        assert r.status_code == 200, r.text
        seq = r.json()
        expected = ("committed", 4, "EPSG:25833", "drive")
        assert (seq["status"], seq["frames"], seq["crs"], seq["platform"]) == expected
        assert (api.storage / "sequences" / sid / "sequence.json").is_file()
        assert not (api.storage / "uploads" / "sequences" / sid).exists()
        assert_problem(c.put(f"/sequences/{sid}/parts/1", content=b"x"), 409)
        assert c.post(f"/sequences/{sid}/commit").json()["id"] == sid  # idempotent
        assert c.get(f"/sequences/{sid}").json()["frames"] == 4
        assert_problem(c.get(f"/sequences/{uuid.uuid4()}"), 404)


def test_part_checksum_gap_and_limit(api: ApiServer) -> None:
    with api.client("submit") as c:
        sid = c.post("/sequences").json()["id"]
        r = c.put(
            f"/sequences/{sid}/parts/1", content=b"abcdef", headers={"Content-MD5": content_md5(b"abcdeX")}
        )
        assert "Content-MD5" in assert_problem(r, 400)["detail"]
        assert_problem(
            c.put(f"/sequences/{sid}/parts/1", content=b"abc", headers={"Content-MD5": "###"}), 400
        )
        assert c.get(f"/sequences/{sid}").json()["parts"] == []
        for n in (1, 3):
            assert c.put(f"/sequences/{sid}/parts/{n}", content=b"abc").status_code == 200
        assert "part 2" in assert_problem(c.post(f"/sequences/{sid}/commit"), 400)["detail"]
        assert_problem(c.put(f"/sequences/{sid}/parts/0", content=b"abc"), 422)
        too_big = b"\0" * (MAX_UPLOAD + 500_000)
        assert_problem(c.put(f"/sequences/{sid}/parts/4", content=too_big), 413)
        chunks = (too_big[i : i + 65536] for i in range(0, len(too_big), 65536))
        assert_problem(c.put(f"/sequences/{sid}/parts/4", content=chunks), 413)
        # the parts together may not pass the limit either
        assert_problem(c.put(f"/sequences/{sid}/parts/2", content=b"\0" * (MAX_UPLOAD - 3)), 413)
        assert [p["n"] for p in c.get(f"/sequences/{sid}").json()["parts"]] == [1, 3]
        assert c.put(f"/sequences/{sid}/parts/2", content=b"abc").status_code == 200
        assert "archive" in assert_problem(c.post(f"/sequences/{sid}/commit"), 422)["detail"]
    parts = sorted(p.name for p in (api.storage / "uploads" / "sequences" / sid).iterdir())
    assert parts == ["part-1", "part-2", "part-3"]
    assert not list((api.storage / "sequences").glob(".tmp-*"))


def test_package_with_a_missing_frame_is_refused(api: ApiServer, synth_package: Path, tmp_path: Path) -> None:
    broken = package_variant(synth_package, tmp_path)
    (broken / "frames" / "000002.png").unlink()
    with api.client("submit") as c:
        sid = upload_parts(c, tar_gz(broken), parts=2)
        assert "frames/000002.png" in assert_problem(c.post(f"/sequences/{sid}/commit"), 422)["detail"]
        view = c.get(f"/sequences/{sid}").json()
        assert view["status"] == "open" and "frames/000002.png" in view["message"]
    assert not (api.storage / "sequences" / sid).exists()
    assert not list((api.storage / "sequences").glob(".tmp-*"))


def test_register_by_path(api: ApiServer, synth_package: Path) -> None:
    inside = api.storage / "incoming" / "drive"
    shutil.copytree(synth_package, inside)
    with api.client("submit") as c:
        assert_problem(c.post("/sequences/register", json={"path": "incoming/drive"}), 403)
    with api.client("admin") as c:
        r = c.post("/sequences/register", json={"path": "incoming/drive"})
        assert r.status_code == 201, r.text
        assert r.json()["frames"] == 4 and r.json()["status"] == "committed"
        assert (
            "storage"
            in assert_problem(c.post("/sequences/register", json={"path": str(synth_package)}), 422)["detail"]
        )
        assert_problem(c.post("/sequences/register", json={"path": "../../etc"}), 422)


# -- abandoned uploads (the sweeper's helper) --------------------------------------------------
def test_remove_abandoned_uploads(api: ApiServer, db_engine) -> None:
    from db.service_records import remove_abandoned_uploads
    from db.settings import Settings

    with api.client("submit") as c:
        old, fresh = (c.post("/sequences").json()["id"] for _ in range(2))
        for sid in (old, fresh):
            assert c.put(f"/sequences/{sid}/parts/1", content=b"abc").status_code == 200
    stray = api.storage / "uploads" / "models" / ".tmp-0123.gml"
    stray.parent.mkdir(parents=True, exist_ok=True)
    stray.write_bytes(b"<")
    os.utime(stray, (time.time() - 7200, time.time() - 7200))
    with db_engine.begin() as conn:
        conn.execute(
            text("UPDATE sequence_upload SET updated_at = now() - interval '2 hours' WHERE id = :i"),
            {"i": old},
        )
    settings = Settings(storage_dir=api.storage, database_url=str(db_engine.url))
    with Session(db_engine) as s:
        done = remove_abandoned_uploads(s, settings, 3600)
    assert old in done.sequence_uploads and fresh not in done.sequence_uploads
    assert str(stray) in done.stray_paths and not stray.exists()
    assert not (api.storage / "uploads" / "sequences" / old).exists()
    assert (api.storage / "uploads" / "sequences" / fresh / "part-1").is_file()
    with api.client("read") as c:
        assert c.get(f"/sequences/{old}").json()["status"] == "failed"
        assert c.get(f"/sequences/{fresh}").json()["status"] == "open"
