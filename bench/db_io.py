"""City model database benchmark: import and export of the replicated NRW model (9,483 buildings
and 4,785 building parts, ~200 MB of CityGML, one file).

Builds the input with `bench/citygml_io.make_replicated_model` (87 shifted copies of the NRW LoD2
tile, 109 buildings + 55 parts each), creates a fresh bench database (`citytherm_bench` on the
server of `CITYTHERM_BENCH_PG`, default `postgresql://postgres@127.0.0.1:5432`), migrates it, then
runs each phase in its own subprocess so that peak RSS figures are the phase's own:

- import: `import_citygml` (reader processes started first, before the database layer loads, as
  `citytherm import` starts them: `db.import_stream.prestart`; COPY batches, one transaction,
  spatial indexes kept):
  buildings/s and parts/s (counted apart) over the phase's whole wall time including the Python
  start-up (`*_per_s`) and over the import call alone (`import_call`), surfaces/s, MB/s; peak RSS
  and CPU seconds of every process: the importer, its reader process and the PostgreSQL backend
  (its RSS includes the shared buffers it touched); the machine's load average, since it is
  shared (wall-clock figures drop when other processes compete for the cores); which compiled parts
  the readers use (`compiled_parts`; `CITYTHERM_NO_COMPILED=1` runs the Python code); and from the CPU
  seconds of those processes (the importer's and the reader's with their start-up) the wall time
  and buildings/s they allow on 2 idle cores (`cpu_budget`); and the start-up of the `citytherm`
  command line, which `citytherm import` pays on top of the phase's own (`cli_startup`);
- export: `export_citygml` of the whole model (streamed, CityGML 2.0 writer): buildings/s, MB/s
  written, peak RSS.

Bars (issue 13): import >= 2,000 buildings/s wall time including start-up, peak RSS of the
importer and of its reader process < 300 MB each.

Usage: `python bench/db_io.py [--copies 87] [--file PATH] [--checks fast|full|none] [--db NAME]
[--keep] [--one-reader] [--check-links] [--split-at F]` (the last three: one reader process
instead of two, the foreign keys checked row by row, as imports were before, and where the file
is cut for the two readers; for comparison) prints JSON
(`--db`: the bench database's name, default `citytherm_bench`; it is dropped and created afresh,
so give one of your own on a shared server).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))
NRW = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"
PG = os.environ.get("CITYTHERM_BENCH_PG", "postgresql://postgres@127.0.0.1:5432")
BENCH_DB = "citytherm_bench"


def _peak_rss_mb() -> float:
    """Peak resident set of this process (MB), `VmHWM` of /proc."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _fresh_database(url_server: str, name: str) -> str:
    import psycopg

    with psycopg.connect(f"{url_server}/postgres", autocommit=True) as conn:
        conn.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,))
        conn.execute(f'DROP DATABASE IF EXISTS "{name}"')
        conn.execute(f'CREATE DATABASE "{name}"')
    url = f"{url_server}/{name}"
    from db.migrations import upgrade

    upgrade(url)
    return url


def _drop_database(url_server: str, name: str) -> None:
    import psycopg

    with psycopg.connect(f"{url_server}/postgres", autocommit=True) as conn:
        conn.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,))
        conn.execute(f'DROP DATABASE IF EXISTS "{name}"')


def _proc_figures(pid: int) -> dict:
    """Peak RSS (MB) and CPU seconds of process `pid` from /proc (None where unreadable)."""
    out: dict = {"peak_rss_mb": None, "cpu_s": None}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                out["peak_rss_mb"] = round(int(line.split()[1]) / 1024.0, 1)
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        out["cpu_s"] = round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 2)
    except (OSError, IndexError, ValueError):
        pass
    return out


def _compiled_parts() -> dict[str, bool]:
    """Which compiled parts of the import the reader processes use (`db.compiled`: built, and not
    turned off with CITYTHERM_NO_COMPILED=1): the geometry walk and the float texts."""
    from importlib.util import find_spec

    from db.compiled import OFF

    return {
        "geometry_walk": not OFF and find_spec("db.citygml._walk") is not None,
        "float_texts": not OFF and find_spec("db._fmt") is not None,
    }


def cpu_budget(cpu_s: dict[str, float], buildings: int, parts: int, cores: int = 2) -> dict:
    """What the CPU seconds of the import's processes allow on `cores` idle cores: the wall time
    cannot be below the total CPU time shared out over the cores, nor below the CPU time of the
    busiest process (a process runs on one core at a time). On a shared machine the measured
    wall time is longer; this bound is what the same work takes without the others' load."""
    total = sum(cpu_s.values())
    wall = max(total / cores, max(cpu_s.values()))
    return {
        "cpu_s_total": round(total, 2),
        "cores": cores,
        "wall_s_lower_bound": round(wall, 2),
        "buildings_per_s_upper_bound": round(buildings / wall, 1) if wall > 0 else None,
        "parts_per_s_upper_bound": round(parts / wall, 1) if wall > 0 else None,
    }


def phase_import(
    url: str,
    path: Path,
    checks: str,
    one_reader: bool = False,
    check_links: bool = False,
    split_at: float | None = None,
) -> dict:
    import resource

    from db.import_options import ImportOptions
    from db.import_stream import prestart

    # as `citytherm import` does: the reader processes start before the database layer is loaded
    opts = ImportOptions(checks=checks, own_links_unchecked=not check_links)
    if split_at is not None:
        opts = dataclasses.replace(opts, split_at=split_at)
    if one_reader:
        opts = dataclasses.replace(opts, split_above_bytes=None)
    readers = prestart(path, opts)

    from sqlalchemy import create_engine, text

    from db.importer import import_citygml
    from db.session import sqlalchemy_url

    # the importer's connections carry this name, so that their backends can be found afterwards
    app = "citytherm-bench-import"
    engine = create_engine(sqlalchemy_url(url), pool_pre_ping=True, connect_args={"application_name": app})
    c0 = time.process_time()
    t0 = time.perf_counter()
    s = import_citygml(engine, path, name="bench", options=opts, readers=readers)
    dt = time.perf_counter() - t0
    cpu_importer = time.process_time() - c0
    reader = resource.getrusage(resource.RUSAGE_CHILDREN)
    with engine.connect() as c:
        pids = c.execute(
            text("SELECT pid FROM pg_stat_activity WHERE application_name = :a AND pid <> pg_backend_pid()"),
            {"a": app},
        ).scalars()
        backends = [_proc_figures(pid) for pid in pids]
        backends.append(_proc_figures(c.execute(text("SELECT pg_backend_pid()")).scalar_one()))
    engine.dispose()
    me = resource.getrusage(resource.RUSAGE_SELF)
    children = reader.ru_utime + reader.ru_stime
    cpu = {
        "importer": me.ru_utime + me.ru_stime,  # with the interpreter's start-up and imports
        # each reader process with its start-up, as it reported it at its end
        **{f"reader_{k + 1}": c for k, c in enumerate(s.reader_cpu_s)},
        # readers that ended without reporting (a split given up): all children minus the above
        "readers_unreported": max(0.0, children - sum(s.reader_cpu_s)),
        "postgres": sum(b["cpu_s"] or 0.0 for b in backends),
    }
    return {
        "buildings": s.buildings,
        "parts": s.parts,
        "surfaces": s.surfaces,
        "import_call": {
            "seconds": round(dt, 2),
            "buildings_per_s": round(s.buildings / dt, 1),
            "parts_per_s": round(s.parts / dt, 1),
        },
        "surfaces_per_s": round(s.surfaces / dt, 1),
        "mb_per_s": round(path.stat().st_size / 1e6 / dt, 2),
        "processes": {
            "importer": {
                "peak_rss_mb": round(_peak_rss_mb(), 1),
                "cpu_s": round(cpu["importer"], 2),
                "cpu_s_import_call": round(cpu_importer, 2),
            },
            "reader": {
                "peak_rss_mb": None if s.reader_peak_rss_mb is None else round(s.reader_peak_rss_mb, 1),
                "cpu_s": round(children, 2),
                "cpu_s_per_process": list(s.reader_cpu_s),
            },
            "postgres_backends": backends,
        },
        "cpu_budget": cpu_budget(cpu, s.buildings, s.parts),
        "timings_s": s.timings_s,
        "checks": checks,
        "reader_processes": len(s.reader_cpu_s),
        "own_links_unchecked": opts.own_links_unchecked,
        "compiled_parts": _compiled_parts(),
        "load_avg_1min_after": round(os.getloadavg()[0], 2),
    }


def phase_export(url: str, out: Path) -> dict:
    import psycopg

    from db.export import export_citygml
    from db.session import psycopg_url

    with psycopg.connect(psycopg_url(url)) as c:
        parts = c.execute("SELECT part_count FROM city_model WHERE name = 'bench'").fetchone()[0]
    t0 = time.perf_counter()
    s = export_citygml(url, out, model="bench")
    dt = time.perf_counter() - t0
    size = s.path.stat().st_size
    return {
        "buildings": s.buildings,
        "parts": parts,
        "seconds": round(dt, 2),
        "buildings_per_s": round(s.buildings / dt, 1),
        "parts_per_s": round(parts / dt, 1),
        "mb_written_per_s": round(size / 1e6 / dt, 2),
        "mb_written": round(size / 1e6, 1),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
    }


def cli_startup() -> dict:
    """Wall and CPU seconds of starting the `citytherm` command line (`from services.cli import
    main`: what `citytherm import` pays before it reads a byte, in a fresh interpreter)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "from services.cli import main"], check=True, cwd=str(REPO))
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2)}


def _run_phase(*args: str) -> dict:
    """Run a phase in a fresh interpreter; its figures plus the wall time of the whole subprocess
    (start-up and imports included)."""
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, __file__, *args], check=True, capture_output=True, text=True, cwd=str(REPO)
    ).stdout
    wall = time.perf_counter() - t0
    return {"wall_s_with_startup": round(wall, 2), **json.loads(out.strip().splitlines()[-1])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=87, help="copies of the NRW tile (87 -> ~14,000 buildings)")
    ap.add_argument("--file", type=Path, help="use this CityGML file instead of building one")
    ap.add_argument("--checks", default="fast", choices=("fast", "full", "none"))
    ap.add_argument("--one-reader", action="store_true", help="one reader process, not one per half")
    ap.add_argument("--check-links", action="store_true", help="check foreign keys row by row")
    ap.add_argument("--split-at", type=float, help="where the file is cut for two readers (fraction)")
    ap.add_argument("--keep", action="store_true", help="keep the bench database and files")
    ap.add_argument("--db", default=BENCH_DB, help="bench database name (dropped and created afresh)")
    ap.add_argument("--phase", choices=("import", "export"), help=argparse.SUPPRESS)
    ap.add_argument("--url", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.phase == "import":
        a = args
        print(json.dumps(phase_import(a.url, a.file, a.checks, a.one_reader, a.check_links, a.split_at)))
        return
    if args.phase == "export":
        print(json.dumps(phase_export(args.url, args.out)))
        return

    tmp = tempfile.TemporaryDirectory(prefix="citytherm-dbbench-")
    big = args.file
    t0 = time.perf_counter()
    if big is None:
        from citygml_io import make_replicated_model

        big = make_replicated_model(NRW, Path(tmp.name) / "nrw-replicated.gml", args.copies)
    build_s = time.perf_counter() - t0
    url = _fresh_database(PG, args.db)
    try:
        load0 = round(os.getloadavg()[0], 2)
        flags = [
            f for f, on in (("--one-reader", args.one_reader), ("--check-links", args.check_links)) if on
        ]
        if args.split_at is not None:
            flags += ["--split-at", str(args.split_at)]
        imp = _run_phase(
            "--phase", "import", "--url", url, "--file", str(big), "--checks", args.checks, *flags
        )
        imp["load_avg_1min_before"] = load0
        imp["cli_startup"] = cli_startup()
        wall = imp["wall_s_with_startup"]
        imp["buildings_per_s"] = round(imp["buildings"] / wall, 1)
        imp["parts_per_s"] = round(imp["parts"] / wall, 1)
        exp = _run_phase("--phase", "export", "--url", url, "--out", str(Path(tmp.name) / "export"))
    finally:
        if not args.keep:
            _drop_database(PG, args.db)
    result = {
        "input": {
            "file_mb": round(big.stat().st_size / 1e6, 1),
            "copies": None if args.file else args.copies,
            "build_seconds": round(build_s, 1),
        },
        "import": imp,
        "export": exp,
        "bars": {
            "import_buildings_per_s_with_startup>=2000": imp["buildings_per_s"] >= 2000,
            "import_peak_rss_mb<300 (importer, reader)": max(
                imp["processes"]["importer"]["peak_rss_mb"], imp["processes"]["reader"]["peak_rss_mb"] or 0
            )
            < 300,
        },
    }
    print(json.dumps(result, indent=1))
    if args.keep:
        print(f"kept: {big} and database {args.db}", file=sys.stderr)
        tmp.cleanup = lambda: None  # type: ignore[method-assign]


if __name__ == "__main__":
    main()
