"""The whole service as a user runs it, over HTTP, and its faults (issue 14).

A stack of its own: a private PostgreSQL + PostGIS server and a private Redis server
(`tests/integration/stack.py`, so that they can be restarted without disturbing anything else),
the API served by `citytherm serve` (uvicorn) and two `citytherm worker` processes (Celery,
prefork), all real processes on loopback.

- End to end: the bundled Berlin model uploaded (`POST /models`), a synthetic drive uploaded in
  chunks and committed, a job submitted with `Prefer: respond-async`, polled to `successful`,
  its results zip fetched: the zip holds what `citytherm run` writes for the same inputs
  (building ids, texture bytes, `textured.gml` members), and PostGIS holds exactly one
  appearance per building.
- Redis restarted in the middle of a job (queued messages lost: no persistence) and PostgreSQL
  restarted in the middle of a job: each job still ends `successful` with exactly one result per
  building and no unit left `running`.
"""

from __future__ import annotations

import io
import os
import subprocess
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import psycopg
import pytest
from lxml import etree

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from tests.integration.conftest import citytherm_exe, content_md5, tar_gz
from tests.integration.stack import PrivatePostgres, PrivateRedis, die_with_tests, free_port, remove
from tests.integration.stack import wait_for as stack_wait_for
from workers.job import RunOptions
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.run import run_job

pytestmark = [pytest.mark.integration, pytest.mark.slow]

#: the Berlin model's: its coordinates are stored as written, so a job's textures are those of
#: `citytherm run` byte for byte (in a database of another SRID the model is stored transformed,
#: its 9-decimal coordinates come back to the micrometre, and a texel can differ by a DN)
SRID = 25833
#: the buildings the jobs texture (as tests/integration/test_workers.py)
BUILDINGS = (
    "BLDG_0003000f001c079c",
    "BLDG_0003000f0008f903",
    "DEB_LOD2_UUID_223c804e-ed2e-4970-b42b-df3fcc4e8b30",
    "DEB_LOD2_UUID_bdba8cdc-80d7-457e-b484-b3c503bab56f",
)
INPUTS = {"resolution": 10, "refine": False, "buildings": list(BUILDINGS)}
OPTIONS = RunOptions.build(resolution_px_per_m=10, refine=False, buildings=BUILDINGS)
PENDING = "SELECT count(*) FROM job_unit WHERE job_id = %s AND status IN ('accepted', 'running')"
#: a bound on every wait (never a timing assertion)
PATIENCE_S = 300.0


def wait_for(what: str, cond: Callable[[], Any]) -> Any:
    """Poll `cond` until it returns something true (`stack.wait_for`, this module's patience)."""
    return stack_wait_for(what, cond, PATIENCE_S)


@dataclass
class Stack:
    """The running service: servers, API, workers, an admin client."""

    pg: PrivatePostgres
    redis: PrivateRedis
    db_url: str
    env: dict[str, str]
    base: str
    key: str
    logs: Path
    procs: dict[str, subprocess.Popen[bytes]]

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.base, headers={"Authorization": f"Bearer {self.key}"}, timeout=120)

    def start(self, name: str, *args: str) -> None:
        with open(self.logs / f"{name}.log", "ab") as log:
            self.procs[name] = subprocess.Popen(
                [citytherm_exe(), *args], env=self.env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True, preexec_fn=die_with_tests,
            )  # fmt: skip

    def sql(self, query: str, *params: Any) -> list[tuple[Any, ...]]:
        with psycopg.connect(self.db_url) as conn:
            return conn.execute(query, params).fetchall()


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    root = tmp_path_factory.mktemp("service-stack")
    pg = PrivatePostgres().init()
    pg.start()
    redis = PrivateRedis(root / "redis")
    redis.start()
    db_url = pg.create_database("citytherm")
    port = free_port()
    env = {
        **os.environ,
        "CITYTHERM_DATABASE_URL": db_url,
        "CITYTHERM_REDIS_URL": redis.url,
        "CITYTHERM_STORAGE_DIR": str(root / "storage"),
        "CITYTHERM_DATABASE_SRID": str(SRID),
        "CITYTHERM_UNIT_TIMEOUT_S": "20",
        "CITYTHERM_SWEEP_INTERVAL_S": "1",
        "CITYTHERM_MIN_FREE_BYTES": "0",
    }
    exe = citytherm_exe()
    subprocess.run([exe, "db", "upgrade"], env=env, check=True, capture_output=True)
    key = subprocess.run(
        [exe, "apikey", "create", "--scope", "admin", "--name", "e2e"],
        env=env, check=True, capture_output=True, text=True,
    ).stdout.strip().splitlines()[-1]  # fmt: skip
    s = Stack(pg, redis, db_url, env, f"http://127.0.0.1:{port}", key, root, {})
    s.start("api", "serve", "--host", "127.0.0.1", "--port", str(port))
    s.start("w1", "worker", "--concurrency", "1", "--hostname", "w1@e2e", "--beat")
    s.start("w2", "worker", "--concurrency", "1", "--hostname", "w2@e2e")
    try:
        wait_for("the API", lambda: httpx.get(f"{s.base}/conformance", timeout=5).status_code == 200)
        yield s
    finally:
        for p in s.procs.values():
            p.terminate()
        for p in s.procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, 9)
                p.wait()
        redis.stop()
        remove(pg)


@dataclass(frozen=True)
class Uploaded:
    model: int
    sequence: str
    package: Path


@pytest.fixture(scope="module")
def uploaded(stack: Stack, tmp_path_factory: pytest.TempPathFactory) -> Uploaded:
    """The Berlin model and a 16-frame drive uploaded through the API (model gzip-encoded; the
    package as a .tar.gz in 4 parts with Content-MD5) and ready."""
    folder = tmp_path_factory.mktemp("e2e-scene")
    _, buildings = read_model(BUNDLED_MODEL)
    opts = SynthOptions(
        n_frames=16, seed=3, buildings=3, frame_interval_s=0.2, errors=ErrorOptions(enabled=False),
        model_path=str(BUNDLED_MODEL),
    )  # fmt: skip
    package = write_synthetic_package(synthesize(buildings, opts), folder / "seq")
    import gzip

    with stack.client() as c:
        r = c.post(
            "/models?name=berlin", content=gzip.compress(BUNDLED_MODEL.read_bytes()),
            headers={"Content-Type": "application/gml+xml", "Content-Encoding": "gzip"},
        )  # fmt: skip
        assert r.status_code == 202, r.text
        model = r.json()["id"]
        assert r.json()["status"] == "importing" and r.headers["Location"].endswith(f"/models/{model}")

        def imported() -> dict[str, Any] | None:
            m = c.get(f"/models/{model}").json()
            return m if m["status"] != "importing" else None

        m = wait_for("the model import", imported)
        assert m["status"] == "ready", m
        data = tar_gz(package)
        sid = c.post("/sequences").json()["id"]
        step = -(-len(data) // 4)
        for n in (3, 1, 4, 2, 2):  # out of order, one part sent twice: the parts' numbers decide
            chunk = data[(n - 1) * step : n * step]
            md5 = {"Content-MD5": content_md5(chunk)}
            r = c.put(f"/sequences/{sid}/parts/{n}", content=chunk, headers=md5)
            assert r.status_code == 200, r.text
        r = c.post(f"/sequences/{sid}/commit")
        assert r.status_code == 200, r.text
        assert r.json()["frames"] == 16 and r.json()["platform"] == "drive"
    return Uploaded(model, sid, package)


@pytest.fixture(scope="module")
def reference(uploaded: Uploaded, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`citytherm run` on the same inputs: its results folder."""
    out = tmp_path_factory.mktemp("e2e-reference") / "results"
    run_job(BUNDLED_MODEL, uploaded.package, out, OPTIONS)
    return out


def submit(stack: Stack, uploaded: Uploaded) -> str:
    with stack.client() as c:
        r = c.post(
            "/processes/texture/execution",
            json={"inputs": {"model": uploaded.model, "sequence": uploaded.sequence, **INPUTS}},
            headers={"Prefer": "respond-async"},
        )
    assert r.status_code == 201, r.text
    body = r.json()
    # a worker may take it up before the answer is made
    assert r.headers["Location"].endswith(f"/jobs/{body['jobID']}")
    assert body["status"] in ("accepted", "running")
    return str(body["jobID"])


def status(stack: Stack, job: str) -> dict[str, Any]:
    with stack.client() as c:
        r = c.get(f"/jobs/{job}")
    assert r.status_code == 200, r.text
    return r.json()


def final(stack: Stack, job: str) -> dict[str, Any]:
    return wait_for(f"job {job} to end", lambda: (s := status(stack, job))["status"] in
                    ("successful", "failed", "dismissed") and s)  # fmt: skip


def assert_one_result_per_building(stack: Stack, job: str) -> None:
    units = stack.sql("SELECT status, count(*) FROM job_unit WHERE job_id = %s GROUP BY status", job)
    assert dict(units) == {"successful": len(BUILDINGS)}, units
    apps = stack.sql(
        "SELECT b.gml_id, count(*) FROM appearance a JOIN building b ON b.id = a.building_id "
        "WHERE a.job_id = %s AND a.theme = 'thermal-ir' GROUP BY b.gml_id",
        job,
    )
    assert sorted(apps) == sorted((b, 1) for b in BUILDINGS), apps
    poses = stack.sql(
        "SELECT count(*), count(DISTINCT (building_id, frame_index)) FROM frame_pose WHERE job_id = %s", job
    )
    assert poses[0][0] == poses[0][1]  # no pose twice


def _members(gml: bytes) -> dict[str, bytes]:
    """Canonical XML of each `bldg:Building` by gml:id."""
    root = etree.fromstring(gml, etree.XMLParser(resolve_entities=False, no_network=True))
    ns = {"bldg": "http://www.opengis.net/citygml/building/2.0", "gml": "http://www.opengis.net/gml"}
    return {
        b.get("{http://www.opengis.net/gml}id"): etree.tostring(b, method="c14n")
        for b in root.iterfind(".//bldg:Building", ns)
    }


def test_end_to_end_over_http_equals_citytherm_run(stack: Stack, uploaded: Uploaded, reference: Path) -> None:
    job = submit(stack, uploaded)
    s = final(stack, job)
    assert s["status"] == "successful", s
    assert s["progress"] == 100
    assert_one_result_per_building(stack, job)
    with stack.client() as c:  # the results document, once the finish task wrote the results
        url = f"/jobs/{job}/results"
        doc = wait_for("results", lambda: (r := c.get(url)).status_code == 200 and r.json())
        zip_link = next(o for o in doc.values() if o["type"] == "application/zip")
        r = c.get(zip_link["href"])
        assert r.status_code == 200 and r.headers["content-type"].startswith("application/zip")
    z = zipfile.ZipFile(io.BytesIO(r.content))
    names = set(z.namelist())
    ref_names = {str(p.relative_to(reference)) for p in reference.rglob("*") if p.is_file()}
    assert names == ref_names
    tiles = sorted(n for n in names if n.startswith("textures/"))
    assert tiles
    for n in tiles:  # texture bytes identical
        assert z.read(n) == (reference / n).read_bytes(), n
    got, want = _members(z.read("textured.gml")), _members((reference / "textured.gml").read_bytes())
    assert got and set(got) <= set(BUILDINGS)  # the buildings the frames textured
    assert got == want


def test_redis_restarted_during_a_job(stack: Stack, uploaded: Uploaded) -> None:
    """Redis stops (its queue is lost: no persistence) while units are queued or running, and
    comes back: the sweeper queues the lost work again from PostGIS."""
    job = submit(stack, uploaded)
    wait_for("units", lambda: stack.sql("SELECT count(*) FROM job_unit WHERE job_id = %s", job)[0][0] > 0)
    stack.redis.stop()
    pending = stack.sql(PENDING, job)
    assert pending[0][0] > 0  # the fault hits the job in the middle
    time.sleep(2.0)  # the workers and the API lose the broker for a while
    stack.redis.start()
    s = final(stack, job)
    assert s["status"] == "successful", s
    assert_one_result_per_building(stack, job)


def test_postgres_restarted_during_a_job(stack: Stack, uploaded: Uploaded) -> None:
    """PostgreSQL stops (open transactions rolled back, connections closed) while units run, and
    comes back: transient database errors are retried, nothing is half-written."""
    job = submit(stack, uploaded)
    started = "SELECT count(*) FROM job_unit WHERE job_id = %s AND status IN ('running', 'successful')"
    wait_for("a running unit", lambda: stack.sql(started, job)[0][0] > 0)
    pending = stack.sql(PENDING, job)
    stack.pg.stop("fast")
    assert pending[0][0] > 0  # the fault hits the job in the middle
    time.sleep(2.0)
    stack.pg.start()
    s = final(stack, job)
    assert s["status"] == "successful", s
    assert_one_result_per_building(stack, job)
    assert stack.sql("SELECT count(*) FROM job_unit WHERE status = 'running'")[0][0] == 0
