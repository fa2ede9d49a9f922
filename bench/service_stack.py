"""The service bench's stack and process figures (`bench/service.py`): a private PostgreSQL +
PostGIS and Redis, the API (`citytherm serve`) and the workers (`citytherm worker`) as
subprocesses (`Stack`), and the CPU seconds and peak RSS of process trees from `/proc`.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import io
import os
import signal
import subprocess
import sys
import tarfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import psycopg

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.integration.stack import PrivatePostgres, PrivateRedis, free_port, remove  # noqa: E402
from tests.integration.stack import wait_for as stack_wait_for  # noqa: E402

SRID = 25833  # the Berlin model's (ETRS89 / UTM 33N): its coordinates are stored as written
EXE = str(Path(sys.executable).with_name("citytherm"))
PATIENCE_S = 1800.0  # a bound on every wait (never a timing figure)
MiB = 1 << 20


def say(msg: str) -> None:
    print(f"[service bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def load() -> float:
    return round(os.getloadavg()[0], 2)


def wait_for(what: str, cond: Callable[[], Any], patience_s: float = PATIENCE_S, step_s: float = 0.2) -> Any:
    """`stack.wait_for` with this bench's patience."""
    return stack_wait_for(what, cond, patience_s, step_s)


def content_md5(data: bytes) -> str:
    """`Content-MD5` (RFC 1864): base64 of the MD5 digest."""
    return base64.b64encode(hashlib.md5(data).digest()).decode()


def tar_bytes(folder: Path, arcname: str = "drive") -> bytes:
    """`folder` as an uncompressed .tar (the frames are PNGs already) in memory."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        tf.add(str(folder), arcname=arcname)
    return buf.getvalue()


def expect(r: httpx.Response, *codes: int) -> httpx.Response:
    if r.status_code not in codes:
        raise RuntimeError(f"{r.request.method} {r.request.url}: {r.status_code} {r.text[:2000]}")
    return r


# -- processes: peak RSS, CPU seconds of process trees -------------------------------------------
CLK = os.sysconf("SC_CLK_TCK")


def peak_rss_mb(pid: int) -> float | None:
    """`VmHWM` of process `pid` in MB (None when unreadable)."""
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024.0, 1)
    return None


def _stat(pid: int) -> tuple[int, float] | None:
    """(parent pid, CPU seconds of the process and its waited-for children)."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return int(f[1]), sum(int(x) for x in f[11:15]) / CLK


def _trees(roots: dict[str, int]) -> tuple[dict[str, list[int]], dict[int, float]]:
    """The live pids of each named process tree, and every process's CPU seconds."""
    parent: dict[int, int] = {}
    cpu: dict[int, float] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit() and (s := _stat(int(d.name))) is not None:
            parent[int(d.name)], cpu[int(d.name)] = s
    kids: dict[int, list[int]] = defaultdict(list)
    for p, pp in parent.items():
        kids[pp].append(p)
    trees = {}
    for name, root in roots.items():
        pids, todo = [], [root]
        while todo:
            p = todo.pop()
            if p in cpu:
                pids.append(p)
                todo += kids.get(p, [])
        trees[name] = pids
    return trees, cpu


def tree_cpu_s(roots: dict[str, int]) -> dict[str, float]:
    """CPU seconds (user + system, reaped children included) of each named process tree."""
    trees, cpu = _trees(roots)
    return {name: sum(cpu[p] for p in pids) for name, pids in trees.items()}


def tree_peak_rss_mb(roots: dict[str, int]) -> dict[str, float | None]:
    """The largest `VmHWM` (MB) among the live processes of each named tree."""
    trees, _ = _trees(roots)
    return {name: max((m for p in pids if (m := peak_rss_mb(p)) is not None), default=None)
            for name, pids in trees.items()}  # fmt: skip


def cpu_delta(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
    return {k: round(after[k] - before.get(k, 0.0), 1) for k in after}


# -- the stack ------------------------------------------------------------------------------------
class Stack:
    """Private PostgreSQL + Redis, the API and the workers, as subprocesses; `close()` stops all."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.logs = root / "logs"
        self.logs.mkdir(parents=True)
        self.pg: PrivatePostgres | None = None
        self.redis: PrivateRedis | None = None
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.env: dict[str, str] = {}
        self.db_url = ""
        self.base = ""
        self.key = ""

    def up(self) -> None:
        self.pg = PrivatePostgres().init()
        self.pg.start()
        self.redis = PrivateRedis(self.root / "redis")
        self.redis.start()
        self.db_url = self.pg.create_database("citytherm")
        self.env = {
            **{k: v for k, v in os.environ.items() if not k.startswith("CITYTHERM_")},
            "CITYTHERM_DATABASE_URL": self.db_url,
            "CITYTHERM_REDIS_URL": self.redis.url,
            "CITYTHERM_STORAGE_DIR": str(self.root / "storage"),
            "CITYTHERM_DATABASE_SRID": str(SRID),
        }
        subprocess.run([EXE, "db", "upgrade"], env=self.env, check=True, capture_output=True)
        self.key = subprocess.run(
            [EXE, "apikey", "create", "--scope", "admin", "--name", "bench"],
            env=self.env, check=True, capture_output=True, text=True,
        ).stdout.strip().splitlines()[-1]  # fmt: skip
        port = free_port()
        self.base = f"http://127.0.0.1:{port}"
        self.start("api", "serve", "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning")
        wait_for("the API", lambda: self.alive("api") and httpx.get(f"{self.base}/conformance", timeout=5)
                 .status_code == 200, patience_s=120)  # fmt: skip

    def start(self, name: str, *args: str) -> None:
        with open(self.logs / f"{name}.log", "ab") as log:
            self.procs[name] = subprocess.Popen(
                [EXE, *args], env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )

    def alive(self, name: str) -> bool:
        p = self.procs.get(name)
        if p is not None and p.poll() is not None:
            raise RuntimeError(f"{name} exited ({p.returncode}):\n{self.log(name)[-3000:]}")
        return p is not None

    def log(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def start_worker(self, name: str, beat: bool, threads: int | None = None) -> None:
        """`citytherm worker --concurrency 1 [--threads T]` (node `<name>@bench`; `threads`: library
        threads per process, None: the command's default, 0: no cap), until it answers a ping."""
        from db.settings import Settings
        from workers.celery_app import configure

        node = f"{name}@bench"
        extra = [*(["--beat"] if beat else []), *([] if threads is None else ["--threads", str(threads)])]
        self.start(name, "worker", "--concurrency", "1", "--hostname", node, *extra)
        app = configure(Settings(redis_url=self.redis.url, database_url=self.db_url))  # type: ignore[union-attr]

        def answers() -> bool:
            self.alive(name)
            return any(node in r for r in app.control.ping(destination=[node], timeout=0.5) or [])

        wait_for(f"worker {name}", answers, patience_s=120)

    def client(self, timeout: float = 300.0) -> httpx.Client:
        return httpx.Client(
            base_url=self.base, headers={"Authorization": f"Bearer {self.key}"}, timeout=timeout
        )

    def sql(self, query: str, *params: Any) -> list[tuple[Any, ...]]:
        with psycopg.connect(self.db_url) as conn:
            return conn.execute(query, params).fetchall()

    def pids(self) -> dict[str, int]:
        """Roots of the process trees to account: API, workers, PostgreSQL (postmaster), Redis."""
        out = {name: p.pid for name, p in self.procs.items() if p.poll() is None}
        if self.pg is not None:
            with contextlib.suppress(OSError, ValueError, IndexError):
                out["postgres"] = int((self.pg.data / "postmaster.pid").read_text().split()[0])
        if self.redis is not None and self.redis.proc is not None:
            out["redis"] = self.redis.proc.pid
        return out

    def close(self) -> None:
        """Stop the API and workers (SIGTERM, then SIGKILL to their process groups), Redis and
        PostgreSQL; remove PostgreSQL's folder."""
        for p in self.procs.values():
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.terminate()
        for p in self.procs.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=15)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)  # the worker's pool children and beat too
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=15)
        if self.redis is not None:
            self.redis.stop()
        if self.pg is not None:
            remove(self.pg)
