"""Integration fixtures: a real PostgreSQL + PostGIS test database and a real Redis db number.

The test database is `citytherm_test` (override with `CITYTHERM_TEST_DATABASE`), created fresh
per session on the server at `CITYTHERM_TEST_PG` (default `postgresql://postgres@127.0.0.1:5432`);
Redis db 15 at `CITYTHERM_TEST_REDIS` (default `redis://127.0.0.1:6379/15`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator

import psycopg
import pytest

from tests.integration.stack import die_with_tests

PG_SERVER = os.environ.get("CITYTHERM_TEST_PG", "postgresql://postgres@127.0.0.1:5432")
TEST_DB = os.environ.get("CITYTHERM_TEST_DATABASE", "citytherm_test")
REDIS_URL = os.environ.get("CITYTHERM_TEST_REDIS", "redis://127.0.0.1:6379/15")
#: the test database's SRID: the bundled Berlin model's (ETRS89 / UTM 33N); NRW and Bavarian models
#: (UTM 32N) are transformed into it on import
TEST_SRID = int(os.environ.get("CITYTHERM_TEST_SRID", "25833"))


def scalar(url: str, sql: str, params: tuple = ()) -> object:
    """The first column of the first row of `sql` on the database at `url` (None: no row)."""
    with psycopg.connect(url, autocommit=True) as c:
        row = c.execute(sql, params).fetchone()
    return None if row is None else row[0]


def _admin_conn() -> psycopg.Connection:
    return psycopg.connect(f"{PG_SERVER}/postgres", autocommit=True)


@pytest.fixture(scope="session")
def pg_test_db() -> Iterator[str]:
    """Create an empty `citytherm_test` database with PostGIS; yield its psycopg URL; drop it after."""
    with _admin_conn() as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (TEST_DB,)
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{TEST_DB}"')
        conn.execute(f'CREATE DATABASE "{TEST_DB}"')
    url = f"{PG_SERVER}/{TEST_DB}"
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    yield url
    with _admin_conn() as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (TEST_DB,)
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{TEST_DB}"')


@pytest.fixture(scope="session")
def redis_url() -> str:
    """URL of the test Redis database (db 15), flushed before use."""
    import redis

    client = redis.Redis.from_url(REDIS_URL)
    client.flushdb()
    return REDIS_URL


@pytest.fixture(scope="session")
def migrated_db(pg_test_db: str) -> str:
    """`pg_test_db` upgraded to the newest schema revision (Alembic); yields the same URL."""
    from db.migrations import upgrade

    upgrade(pg_test_db, srid=TEST_SRID)
    return pg_test_db


@pytest.fixture(scope="session")
def db_engine(migrated_db: str) -> Iterator[object]:
    """A SQLAlchemy engine (psycopg 3) on the migrated test database."""
    from db.session import make_engine

    engine = make_engine(migrated_db)
    yield engine
    engine.dispose()


# -- the service's workers (tests/integration/test_workers.py) ----------------------------------
#: short enough that the sweeper takes over a killed worker's unit within seconds, long enough
#: for a unit of the small test scenes on a loaded machine (the hard limit adds 5 s)
WORKER_UNIT_TIMEOUT_S = 20


@pytest.fixture(scope="session")
def storage_dir(tmp_path_factory: pytest.TempPathFactory) -> object:
    """An empty service storage directory (`CITYTHERM_STORAGE_DIR`)."""
    return tmp_path_factory.mktemp("storage")


@pytest.fixture(scope="session")
def service_env(migrated_db: str, redis_url: str, storage_dir: object) -> Iterator[dict[str, str]]:
    """The service's settings as environment variables (test database, test Redis db, storage,
    a short unit timeout and sweep interval), also set in this process while the session runs
    (the Celery app is configured from them). Yields the variables."""
    from workers.celery_app import configure

    env = {
        "CITYTHERM_DATABASE_URL": migrated_db,
        "CITYTHERM_REDIS_URL": redis_url,
        "CITYTHERM_STORAGE_DIR": str(storage_dir),
        "CITYTHERM_DATABASE_SRID": str(TEST_SRID),
        "CITYTHERM_UNIT_TIMEOUT_S": str(WORKER_UNIT_TIMEOUT_S),
        "CITYTHERM_SWEEP_INTERVAL_S": "1",
        "CITYTHERM_TASK_MAX_RETRIES": "2",
        "CITYTHERM_WORKER_CONCURRENCY": "1",
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    configure()
    yield env
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class CeleryWorkers:
    """Real `citytherm worker` processes (prefork, one child each), each in its own process group,
    logging to `<log_dir>/<name>.log`; the first one also runs the sweeper (`--beat`)."""

    def __init__(self, env: dict[str, str], log_dir: object, names: tuple[str, ...]) -> None:
        import subprocess
        import sys
        from pathlib import Path

        self.subprocess = subprocess
        self.env = {**os.environ, **env}
        self.log_dir = Path(str(log_dir))
        self.names = names
        self.exe = str(Path(sys.executable).with_name("citytherm"))
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def log(self, name: str) -> str:
        """What worker `name` logged so far (all its runs)."""
        path = self.log_dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def start(self, name: str) -> None:
        """Start worker `name` (node name `<name>@citytherm-test`) and wait until it answers a ping."""
        import time

        from workers.celery_app import app

        beat = ["--beat"] if name == self.names[0] else []
        with open(self.log_dir / f"{name}.log", "ab") as log:
            self.procs[name] = self.subprocess.Popen(
                [self.exe, "worker", "--concurrency", "1", "--hostname", f"{name}@citytherm-test", *beat],
                env=self.env,
                stdout=log,
                stderr=self.subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=die_with_tests,
            )
        node = f"{name}@citytherm-test"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.procs[name].poll() is not None:
                raise RuntimeError(f"worker {name} exited:\n{self.log(name)[-3000:]}")
            if any(node in r for r in app.control.ping(destination=[node], timeout=0.5) or []):
                return
        raise RuntimeError(f"worker {name} did not answer:\n{self.log(name)[-3000:]}")

    def alive(self, name: str) -> bool:
        """True while worker `name`'s main process runs."""
        return name in self.procs and self.procs[name].poll() is None

    def kill(self, name: str) -> None:
        """SIGKILL worker `name`'s whole process group (main process and pool children)."""
        import contextlib
        import signal

        proc = self.procs[name]
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)

    def ensure(self) -> None:
        """Start the workers that do not run."""
        for name in self.names:
            if not self.alive(name):
                self.start(name)

    def stop(self) -> None:
        """Stop every worker (SIGTERM, then SIGKILL to the process group)."""
        import contextlib

        for proc in self.procs.values():
            if proc.poll() is None:
                proc.terminate()
        for name, proc in self.procs.items():
            with contextlib.suppress(self.subprocess.TimeoutExpired):
                proc.wait(timeout=10)
            self.kill(name)


@pytest.fixture(scope="session")
def celery_workers(
    service_env: dict[str, str], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[CeleryWorkers]:
    """TWO real Celery worker processes (`citytherm worker`) on the test database, Redis db and
    storage; the first also runs the sweeper. Killed at teardown."""
    workers = CeleryWorkers(service_env, tmp_path_factory.mktemp("worker-logs"), ("w1", "w2"))
    try:
        workers.ensure()
        yield workers
    finally:
        workers.stop()


# -- the HTTP API (tests/integration/test_api.py) -----------------------------------------------
class ApiServer:
    """A running `citytherm serve` (base URL, storage folder, environment, log) and API keys."""

    def __init__(self, base: str, storage: object, keys: dict[str, str], env: dict[str, str]) -> None:
        from pathlib import Path

        self.base, self.storage, self.keys, self.env = base, Path(str(storage)), keys, env

    def client(self, scope: str | None = "admin") -> object:
        """An httpx client with the bearer key of `scope` (None: without a key)."""
        import httpx

        headers = {"Authorization": f"Bearer {self.keys[scope]}"} if scope else {}
        return httpx.Client(base_url=self.base, headers=headers, timeout=120)


def citytherm_exe() -> str:
    """The `citytherm` console script of this virtual environment."""
    import sys
    from pathlib import Path

    return str(Path(sys.executable).with_name("citytherm"))


def api_env(db_url: str, redis_url: str, storage: object, **settings: object) -> dict[str, str]:
    """This process's environment with the service's settings (`CITYTHERM_<NAME>`)."""
    env = {**os.environ, "CITYTHERM_DATABASE_URL": db_url, "CITYTHERM_REDIS_URL": redis_url}
    env["CITYTHERM_STORAGE_DIR"] = str(storage)
    env.update({f"CITYTHERM_{k.upper()}": str(v) for k, v in settings.items()})
    return env


def new_api_key(env: dict[str, str], *scopes: str) -> str:
    """A new API key from `citytherm apikey create` (its last output line)."""
    import subprocess

    args = [citytherm_exe(), "apikey", "create", "--name", "test"]
    for s in scopes:
        args += ["--scope", s]
    out = subprocess.run(args, env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def api_server_factory(
    migrated_db: str, redis_url: str, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[object]:
    """`start(**settings) -> ApiServer`: `citytherm serve` on a free port of 127.0.0.1, its own
    storage folder, keys for read, submit and admin (made once; one database). The servers are
    stopped, and the tasks they queued purged from the test Redis, at the end of the module."""
    import socket
    import subprocess
    import time

    import httpx

    procs: list[subprocess.Popen[bytes]] = []
    keys: dict[str, str] = {}

    def start(**settings: object) -> ApiServer:
        storage = tmp_path_factory.mktemp("api-storage")
        env = api_env(migrated_db, redis_url, storage, **{"min_free_bytes": 0, **settings})
        keys.update(keys or {s: new_api_key(env, s) for s in ("read", "submit", "admin")})
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        log = storage.parent / f"{storage.name}.log"
        with open(log, "wb") as out:
            cmd = [
                citytherm_exe(),
                "serve",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--log-level",
                "warning",
            ]
            proc = subprocess.Popen(
                cmd, env=env, stdout=out, stderr=subprocess.STDOUT, preexec_fn=die_with_tests
            )
            procs.append(proc)
        base = f"http://127.0.0.1:{port}"
        for _ in range(1200):  # until it listens (a bound on waiting, not a timing assertion)
            if procs[-1].poll() is not None:
                raise RuntimeError(f"the API server exited:\n{log.read_text()}")
            try:
                if httpx.get(f"{base}/openapi.json", timeout=5).status_code == 200:
                    return ApiServer(base, storage, dict(keys), env)
            except httpx.TransportError:
                time.sleep(0.1)
        raise RuntimeError(f"the API server did not start:\n{log.read_text()}")

    yield start
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
    from kombu import Connection

    from workers.celery_app import QUEUE

    with Connection(redis_url) as conn:  # no worker of a later module gets this module's tasks
        conn.default_channel.queue_purge(QUEUE)


@pytest.fixture(scope="session")
def synth_package(tmp_path_factory: pytest.TempPathFactory) -> object:
    """A small synthetic drive past the bundled Berlin model (`citytherm synth`: 4 frames,
    EPSG:25833): the package folder."""
    import subprocess

    out = tmp_path_factory.mktemp("synth") / "seq"
    cmd = [citytherm_exe(), "synth", "-o", str(out), "--frames", "4", "--buildings", "1", "--seed", "2"]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def tar_gz(folder: object, arcname: str = "drive") -> bytes:
    """`folder` as a .tar.gz archive (in memory) whose single top-level folder is `arcname`."""
    import io
    import tarfile

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        tf.add(str(folder), arcname=arcname)
    return buf.getvalue()


def package_variant(package_dir: object, dest: object, **manifest: object) -> object:
    """A copy of a package folder at `dest/variant` with manifest fields replaced."""
    import json
    import shutil
    from pathlib import Path

    out = Path(str(dest)) / "variant"
    shutil.copytree(str(package_dir), out)
    d = json.loads((out / "sequence.json").read_text())
    d.update(manifest)
    (out / "sequence.json").write_text(json.dumps(d))
    return out


def content_md5(data: bytes) -> str:
    """`Content-MD5` of `data` (RFC 1864: base64 of the MD5 digest)."""
    import base64
    import hashlib

    return base64.b64encode(hashlib.md5(data).digest()).decode()


def upload_parts(client: object, data: bytes, parts: int = 3) -> str:
    """Open a sequence upload and send `data` in `parts` parts (with Content-MD5); its id."""
    r = client.post("/sequences")  # type: ignore[attr-defined]
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    step = -(-len(data) // parts)
    for n in range(parts):
        chunk = data[n * step : (n + 1) * step]
        headers = {"Content-MD5": content_md5(chunk)}
        r = client.put(f"/sequences/{sid}/parts/{n + 1}", content=chunk, headers=headers)  # type: ignore[attr-defined]
        assert r.status_code == 200, r.text
    return sid


def assert_problem(response: object, status: int) -> dict:
    """Assert an RFC 7807 problem response of `status`; returns its body."""
    r = response
    assert r.status_code == status, r.text  # type: ignore[attr-defined]
    assert r.headers["content-type"].startswith("application/problem+json")  # type: ignore[attr-defined]
    body = r.json()  # type: ignore[attr-defined]
    assert body["status"] == status and body["title"] and body["type"]
    return body


def ready_api_model(engine: object, name: str) -> tuple[int, int]:
    """The bundled Berlin model imported directly and recorded as a ready API model (a
    `model_import` row): (API model id, city model id)."""
    from sqlalchemy import text

    from db.importer import import_citygml
    from workers.pipeline.synth import BUNDLED_MODEL

    summary = import_citygml(engine, BUNDLED_MODEL, name=name)
    with engine.begin() as conn:  # type: ignore[attr-defined]
        mid = conn.execute(
            text(
                "INSERT INTO model_import (name, status, city_model_id, bytes, progress) "
                "VALUES (:n, 'ready', :m, 0, 1) RETURNING id"
            ),
            {"n": name, "m": summary.model_id},
        ).scalar_one()
    return int(mid), int(summary.model_id)


# -- the API server of the API tests (test_api.py, test_api_uploads.py) ------------------------
#: largest upload of the API tests' server
MAX_UPLOAD = 3_000_000  # bytes: the Berlin model (0.9 MB) and the small package fit, 3.5 MB does not


@pytest.fixture(scope="module")
def make_api(api_server_factory) -> Callable[..., ApiServer]:
    """Start a server: uploads up to `MAX_UPLOAD` bytes, other settings as given."""
    return lambda **settings: api_server_factory(max_upload_bytes=MAX_UPLOAD, **settings)


@pytest.fixture(scope="module")
def api(make_api) -> ApiServer:
    """The API: reads need a key."""
    return make_api()
