"""A private PostgreSQL + PostGIS server and a private Redis server for tests that restart them.

Fault tests restart the database and the broker in the middle of a job; doing that to the
machine's shared servers would break every other client, so these tests start their own: a
PostgreSQL cluster made with `initdb` in a temporary folder (run as the `postgres` user when the
tests run as root, since PostgreSQL refuses root) and a `redis-server` without persistence, each
on a free loopback port. Both are real servers of the versions the machine has; nothing is mocked.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

PG_BIN = Path(os.environ.get("CITYTHERM_TEST_PG_BIN", "/usr/lib/postgresql/15/bin"))


def wait_for(what: str, cond: Callable[[], Any], patience_s: float = 300.0, step_s: float = 0.2) -> Any:
    """Poll `cond` until it returns something true; a connection refused or dropped (an HTTP
    transport error, `OSError`) counts as "not yet". Raises `TimeoutError` after `patience_s`
    (a bound on waiting, never a timing assertion)."""
    import httpx

    deadline = time.monotonic() + patience_s
    while time.monotonic() < deadline:
        try:
            got = cond()
        except (httpx.TransportError, OSError):
            got = None
        if got:
            return got
        time.sleep(step_s)
    raise TimeoutError(f"gave up waiting for {what}")


def die_with_tests() -> None:
    """`preexec_fn` of every server and worker the tests start: the child gets SIGTERM when the
    pytest process that started it ends, however it ends (SIGKILL included), through Linux
    `PR_SET_PDEATHSIG`; so no worker or server outlives an interrupted test run."""
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for_port(port: int, timeout_s: float = 30.0) -> None:
    """Wait until something accepts connections on 127.0.0.1:`port`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


def _as_postgres(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


class PrivatePostgres:
    """A PostgreSQL cluster of its own on `port` (trust authentication, fsync off), in a new
    folder of the system's temporary directory (which the `postgres` user can reach)."""

    def __init__(self, port: int | None = None) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="citytherm-pg-"))
        self.data = self.root / "pgdata"
        self.port = port or free_port()
        self.log = self.root / "postgres.log"

    @property
    def server_url(self) -> str:
        """libpq URL of the server (no database)."""
        return f"postgresql://postgres@127.0.0.1:{self.port}"

    def url(self, database: str) -> str:
        """psycopg URL of `database` on this server."""
        return f"{self.server_url}/{database}"

    def init(self) -> PrivatePostgres:
        """`initdb` the cluster (the folder is given to the `postgres` user when running as root)."""
        if os.geteuid() == 0:
            shutil.chown(self.root, "postgres", "postgres")
        subprocess.run(
            _as_postgres([str(PG_BIN / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust",
                          "--no-sync", "-E", "UTF8"]),
            check=True, capture_output=True, timeout=120,
        )  # fmt: skip
        return self

    def start(self) -> None:
        """Start the server and wait until it accepts connections."""
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=off"
        subprocess.run(
            _as_postgres([str(PG_BIN / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-o", opts,
                          "-w", "-t", "60", "start"]),
            check=True, capture_output=True, timeout=90,
        )  # fmt: skip
        wait_for_port(self.port)

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (`fast`: roll back open transactions, close sessions; `immediate`: as a
        crash would)."""
        subprocess.run(
            _as_postgres([str(PG_BIN / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "stop"]),
            check=False, capture_output=True, timeout=90,
        )  # fmt: skip

    def create_database(self, name: str) -> str:
        """A new database with PostGIS; returns its URL."""
        import psycopg

        with psycopg.connect(f"{self.server_url}/postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        with psycopg.connect(self.url(name), autocommit=True) as conn:
            conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
        return self.url(name)


class PrivateRedis:
    """A `redis-server` of its own on `port`, without persistence."""

    def __init__(self, root: Path, port: int | None = None) -> None:
        self.root = root
        self.port = port or free_port()
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """Redis URL of database 0."""
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        """Start the server and wait until it accepts connections."""
        self.root.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
             "--appendonly", "no", "--dir", str(self.root), "--logfile", str(self.root / "redis.log")],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=die_with_tests,
        )  # fmt: skip
        wait_for_port(self.port)

    def stop(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL); queued messages are lost, as in a crash
        without persistence."""
        if self.proc is None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc = None


def remove(pg: PrivatePostgres) -> None:
    """Stop the server (immediately) and delete its folder."""
    pg.stop("immediate")
    shutil.rmtree(pg.root, ignore_errors=True)
