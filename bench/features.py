"""OGC API - Features benchmark: latency of 100-feature pages of `facades` with 20 concurrent
clients, at the first page and deep in the collection (after 9,900 features, through the keyset
cursor of the `next` links), against `citytherm serve` over HTTP.

Data: the replicated NRW model (`bench/citygml_io.make_replicated_model`: 87 shifted copies of the
NRW LoD2 tile, ~9,500 buildings + parts, ~126,000 surfaces; `--copies 8` for a quick run) imported
into a fresh bench database, with one job's thermal statistics for every surface written in SQL
(as `tests/integration/test_api_features.py` does) and their feature texts (as `db.store` writes
them with the statistics, `db.facade_features`): one facade feature per surface.

Clients: threads, each with its own keep-alive connection of the standard library's
`http.client` (`--client httpx`: httpx clients, as earlier versions of this bench; they cost
1.3-1.9 ms CPU per request against 0.3 ms, on the cores the server and PostgreSQL share), each
waiting for its response (checked: 200, `"numberReturned":100`) before its next request.

Figures (JSON): per phase, requests, p50 / p95 / p99 / max latency (ms) and requests/s (also
with one client: a request's cost without queueing), and the CPU ms per request of the server
(its processes), of PostgreSQL (`postgres`: the backends connected to the bench database, i.e.
the server's queries; `postgres_machine`: all its processes on the machine) and of the clients
(this process): unlike latencies on a shared machine, these hardly depend on the other load; the
single cold first-page request (its numberMatched counted; later first pages reuse the count for
`COUNT_TTL_S` seconds, deep pages carry it in the cursor); the load average of the machine.
Bar (issue 17): p95 < 100 ms at the first page and deep.

Usage: `python bench/features.py [--copies 87] [--clients 20] [--requests 40] [--workers 2]
[--pool-size N] [--db NAME] [--keep] [--reuse] [--client http.client|httpx]` (`--db`: the bench
database, dropped and created afresh; default `citytherm_bench_features`; `--keep` leaves it,
`--reuse` serves it again without importing; `--pool-size`: the same app with a larger
connection pool).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))
NRW = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"
PG = os.environ.get("CITYTHERM_BENCH_PG", "postgresql://postgres@127.0.0.1:5432")
EXE = str(Path(sys.executable).with_name("citytherm"))


def load(url: str, path: Path) -> dict:
    """Import `path` and give every surface one job's thermal statistics; figures."""
    from sqlalchemy import text
    from sqlalchemy.orm import Session

    from db.facade_features import write_feature_texts
    from db.importer import import_citygml
    from db.session import make_engine
    from db.store import create_job

    engine = make_engine(url)
    t0 = time.perf_counter()
    model = import_citygml(engine, path, name="bench").model_id
    t_import = time.perf_counter() - t0
    with Session(engine) as s:
        job = create_job(s, model_id=model, theme="tir-bench")
        s.commit()
    with engine.begin() as c:
        c.execute(
            text(
                "INSERT INTO appearance (city_model_id, building_id, job_id, theme, ordinal) "
                "SELECT b.city_model_id, b.id, :j, 'tir-bench', 0 FROM building b "
                "WHERE b.city_model_id = :m AND b.parent_id IS NULL"
            ),
            {"j": job, "m": model},
        )
        c.execute(
            text(
                "INSERT INTO surface_thermal (appearance_id, surface_id, texels_total, texels_observed, "
                "observed_share, frames_used, resolution_m, mean_k, min_k, max_k, p95_k, temperature, "
                "unit) SELECT a.id, s.id, 100, 80, 0.8, ARRAY[1, 2], 0.05, 270 + (s.id % 20), 260, 300, "
                "290, '{}'::jsonb, 'kelvin' FROM appearance a JOIN building p ON p.root_id = a.building_id "
                "JOIN surface s ON s.building_id = p.id WHERE a.job_id = :j"
            ),
            {"j": job},
        )
        write_feature_texts(c, "TRUE")  # as `db.store` does with the statistics it writes
    with engine.connect() as c:
        # the texts were written by an UPDATE: its dead rows gone, as autovacuum leaves a database
        c.execution_options(isolation_level="AUTOCOMMIT").execute(text("VACUUM ANALYZE"))
        facades = c.execute(text("SELECT count(*) FROM surface_thermal")).scalar_one()
    engine.dispose()
    return {"import_s": round(t_import, 1), "facades": int(facades)}


def make_app() -> object:
    """The API app as `citytherm serve` builds it, but with a connection pool of
    `CITYTHERM_BENCH_POOL_SIZE` connections (`--pool-size`: what a larger pool than the engine's
    default of 5 + 10 overflow would give; uvicorn factory)."""
    from sqlalchemy import create_engine
    from sqlalchemy.orm import sessionmaker

    from db.session import sqlalchemy_url
    from db.settings import Settings
    from services.api.app import create_app

    settings = Settings()
    app = create_app(settings)
    size = int(os.environ["CITYTHERM_BENCH_POOL_SIZE"])
    engine = create_engine(
        sqlalchemy_url(settings.database_url), pool_pre_ping=True, pool_size=size, max_overflow=10
    )
    app.state.engine = engine
    app.state.session_factory = sessionmaker(bind=engine, expire_on_commit=False)
    return app


def start_server(
    url: str, workers: int, log: Path, pool_size: int | None
) -> tuple[subprocess.Popen[bytes], str, str]:
    """`citytherm serve` (or the same app with a pool of `pool_size`) on a free port with a new
    read key: (process, base URL, key)."""
    import httpx

    env = {**os.environ, "CITYTHERM_DATABASE_URL": url, "CITYTHERM_STORAGE_DIR": str(log.parent)}
    key = subprocess.run(
        [EXE, "apikey", "create", "--name", "bench", "--scope", "read"],
        env=env, capture_output=True, text=True, check=True,
    ).stdout.strip().splitlines()[-1]  # fmt: skip
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cmd = [EXE, "serve", "--port", str(port), "--workers", str(workers), "--log-level", "warning"]
    if pool_size:
        env["CITYTHERM_BENCH_POOL_SIZE"] = str(pool_size)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(REPO / "bench"), env.get("PYTHONPATH", "")])
        run = (
            "import uvicorn; uvicorn.run('features:make_app', factory=True, host='127.0.0.1', "
            f"port={port}, workers={workers}, log_level='warning')"
        )
        cmd = [sys.executable, "-c", run]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            if httpx.get(f"{base}/conformance", timeout=2).status_code == 200:
                return proc, base, key
        except httpx.TransportError:
            time.sleep(0.1)
    proc.terminate()
    raise RuntimeError(f"the API server did not start: {log.read_text()}")


def _auth(key: str | None) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"} if key else {}


def _http_client_session(base: str, key: str | None) -> Callable[[str], tuple[int, bytes]]:
    """A keep-alive connection of the standard library's `http.client` (C-parsed headers, little
    Python per request): a function GET path -> (status, body)."""
    import http.client
    from urllib.parse import urlsplit

    u = urlsplit(base)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=60)
    headers = _auth(key)

    def get(path: str) -> tuple[int, bytes]:
        conn.request("GET", path, headers=headers)
        r = conn.getresponse()
        return r.status, r.read()

    return get


def _httpx_session(base: str, key: str | None) -> Callable[[str], tuple[int, bytes]]:
    """A keep-alive `httpx.Client`: a function GET path -> (status, body)."""
    import httpx

    c = httpx.Client(base_url=base, headers=_auth(key), timeout=60)

    def get(path: str) -> tuple[int, bytes]:
        r = c.get(path)
        return r.status_code, r.content

    return get


CLIENTS = {"http.client": _http_client_session, "httpx": _httpx_session}


def hammer(
    base: str, key: str | None, url: str, clients: int, requests: int, kind: str = "http.client"
) -> dict:
    """`clients` threads, each with its own keep-alive connection (`kind`: "http.client", the
    default, or "httpx"), GET `url` `requests` times; latency figures. Each response must be a
    200 with `"numberReturned":100` in its body (else counted as an error)."""
    lat: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()
    barrier = threading.Barrier(clients)

    def client() -> None:
        mine: list[float] = []
        get = CLIENTS[kind](base, key)
        get("/conformance")  # connect before the clock starts
        barrier.wait()
        for _ in range(requests):
            t0 = time.perf_counter()
            status, body = get(url)
            mine.append(time.perf_counter() - t0)
            if status != 200 or b'"numberReturned":100' not in body:
                errors.append(f"{status} {body[:200]!r}")
        with lock:
            lat.extend(mine)

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    lat.sort()

    def q(p: float) -> float:
        return round(1000 * lat[min(len(lat) - 1, int(p * len(lat)))], 1)

    return {
        "requests": len(lat),
        "errors": len(errors),
        "p50_ms": q(0.50),
        "p95_ms": q(0.95),
        "p99_ms": q(0.99),
        "max_ms": round(1000 * lat[-1], 1),
        "requests_per_s": round(len(lat) / wall, 1),
    }


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process `pid` so far (0 when it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _processes() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command name) of every process (Linux `/proc`)."""
    out: dict[int, tuple[int, str]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    head, rest = f.read().rsplit(")", 1)
                out[int(d)] = (int(rest.split()[1]), head.split("(", 1)[1])
            except (OSError, IndexError, ValueError):
                continue
    return out


def _bench_backends(url: str) -> list[int]:
    """pids of the PostgreSQL backends connected to the bench database `url` (the server's
    connection pools; not this query's own backend)."""
    import psycopg

    from db.session import psycopg_url

    with psycopg.connect(psycopg_url(url), autocommit=True) as c:
        rows = c.execute(
            "SELECT pid FROM pg_stat_activity WHERE datname = current_database() "
            "AND backend_type = 'client backend' AND pid <> pg_backend_pid()"
        ).fetchall()
    return [int(r[0]) for r in rows]


def cpu_snapshot(server_pid: int, url: str) -> dict[str, Any]:
    """CPU seconds so far of the server (its process and descendants), of each PostgreSQL
    backend connected to the bench database (`postgres`: pid -> seconds; the work of the
    server's queries, whoever else uses the machine), of every PostgreSQL process of the machine
    (`postgres_machine`: other work's queries included) and of this process (the clients)."""
    procs = _processes()
    tree, todo = {server_pid}, [server_pid]
    while todo:
        parent = todo.pop()
        kids = [p for p, (pp, _) in procs.items() if pp == parent and p not in tree]
        tree.update(kids)
        todo += kids
    return {
        "server": sum(_cpu_s(p) for p in tree),
        "postgres": {p: _cpu_s(p) for p in _bench_backends(url)},
        "postgres_machine": sum(_cpu_s(p) for p, (_, name) in procs.items() if name == "postgres"),
        "client": sum(os.times()[:2]),
    }


def cpu_per_request(before: dict[str, Any], after: dict[str, Any], requests: int) -> dict[str, float]:
    """CPU ms per request of each party between two `cpu_snapshot`s (independent of the
    machine's other load, unlike latencies; but for `postgres_machine`). A bench backend that
    appeared in between counts from its start; one that ended in between is missed (the pool
    keeps its connections, so there are none in practice)."""
    out: dict[str, float] = {}
    for k, v in after.items():
        pg = k == "postgres"
        spent = sum(t - before[k].get(pid, 0.0) for pid, t in v.items()) if pg else v - before[k]
        out[k] = round(1000 * spent / max(requests, 1), 2)
    return out


def deep_url(base: str, key: str | None, path: str, skip: int, limit: int) -> str:
    """The `next` link reached after `skip` features, pages of `limit`, followed like a client."""
    import httpx

    with httpx.Client(base_url=base, headers=_auth(key), timeout=60) as c:
        url = f"{path}?limit={limit}"
        for _ in range(skip // limit):
            doc = c.get(url).json()
            url = next(link["href"] for link in doc["links"] if link["rel"] == "next")
    return url


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=87, help="copies of the NRW tile (8: a quick run)")
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument("--requests", type=int, default=40, help="requests per client and phase")
    ap.add_argument("--workers", type=int, default=2, help="uvicorn worker processes")
    ap.add_argument("--pool-size", type=int, help="serve with a database pool of this size (what-if)")
    ap.add_argument("--deep", type=int, default=9_900, help="features before the deep page")
    ap.add_argument("--db", default="citytherm_bench_features", help="bench database (dropped, created)")
    ap.add_argument("--keep", action="store_true", help="keep the bench database")
    ap.add_argument("--reuse", action="store_true", help="serve the bench database a --keep run left")
    ap.add_argument("--client", choices=sorted(CLIENTS), default="http.client", help="clients' HTTP library")
    args = ap.parse_args()

    from citygml_io import make_replicated_model
    from db_io import _drop_database, _fresh_database

    tmp = tempfile.TemporaryDirectory(prefix="citytherm-featbench-")
    if args.reuse:
        url = f"{PG.rstrip('/')}/{args.db}"
        data = {"reused": args.db}
    else:
        big = make_replicated_model(NRW, Path(tmp.name) / "nrw-replicated.gml", args.copies)
        url = _fresh_database(PG, args.db)
    proc = None
    try:
        if not args.reuse:
            data = load(url, big)
        proc, base, key = start_server(url, args.workers, Path(tmp.name) / "serve.log", args.pool_size)
        import httpx

        path = "/collections/facades/items"
        headers = {"Authorization": f"Bearer {key}"}
        t0 = time.perf_counter()
        cold = httpx.get(f"{base}{path}?limit=100", headers=headers, timeout=60)
        cold_ms = round(1000 * (time.perf_counter() - t0), 1)
        matched = cold.json().get("numberMatched")
        deep = deep_url(base, key, path, args.deep, 100)
        first_url, kind = f"{path}?limit=100", args.client
        for u in (first_url, deep):  # warm-up: connections, plans
            hammer(base, key, u, args.clients, 5, kind)
        c0 = cpu_snapshot(proc.pid, url)
        first = hammer(base, key, first_url, args.clients, args.requests, kind)
        c1 = cpu_snapshot(proc.pid, url)
        deep_fig = hammer(base, key, deep, args.clients, args.requests, kind)
        c2 = cpu_snapshot(proc.pid, url)
        first["cpu_ms_per_request"] = cpu_per_request(c0, c1, first["requests"])
        deep_fig["cpu_ms_per_request"] = cpu_per_request(c1, c2, deep_fig["requests"])
        alone = {  # one client: the cost of a request without queueing
            "first_page": hammer(base, key, first_url, 1, args.requests, kind),
            f"after_{args.deep}": hammer(base, key, deep, 1, args.requests, kind),
        }
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=30)
        if not (args.keep or args.reuse):
            _drop_database(PG, args.db)
    out = {
        "data": {"copies": args.copies, **data, "numberMatched": matched},
        "server": {
            "uvicorn_workers": args.workers,
            "db_pool_size": args.pool_size or "default (CITYTHERM_DATABASE_POOL_SIZE 20 + 10 overflow)",
            "clients": args.clients,
            "client_library": args.client,
            "page": 100,
        },
        "cold_first_page_ms": cold_ms,
        "first_page": first,
        f"after_{args.deep}": deep_fig,
        "one_client": alone,
        "load_avg_1min_after": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
        "bars": {
            "first_page_p95_ms<100": first["p95_ms"] < 100,
            "deep_page_p95_ms<100": deep_fig["p95_ms"] < 100,
        },
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
