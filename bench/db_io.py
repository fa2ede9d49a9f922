"""City model database benchmark: import and export of the replicated NRW model (~14,000
buildings and building parts, ~200 MB of CityGML).

Builds the input with `bench/citygml_io.make_replicated_model` (87 shifted copies of the NRW LoD2
tile: 9,483 buildings + 4,785 parts), creates a fresh bench database (`citytherm_bench` on the
server of `CITYTHERM_BENCH_PG`, default `postgresql://postgres@127.0.0.1:5432`), migrates it, then
runs each phase in its own subprocess so that peak RSS figures are the phase's own:

- import: `import_citygml` (streamed reader, COPY batches, deferred spatial indexes for big files):
  buildings/s (top-level + parts), surfaces/s, MB/s, peak RSS;
- export: `export_citygml` of the whole model (streamed, CityGML 2.0 writer): buildings/s, MB/s
  written, peak RSS.

Bars (issue 7): import >= 1,000 buildings/s, importer peak RSS < 500 MB.

Usage: `python bench/db_io.py [--copies 87] [--file PATH] [--checks fast|full|none] [--keep]`
prints JSON.
"""

from __future__ import annotations

import argparse
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


def phase_import(url: str, path: Path, checks: str) -> dict:
    from db.importer import ImportOptions, import_citygml

    t0 = time.perf_counter()
    s = import_citygml(url, path, name="bench", options=ImportOptions(checks=checks))
    dt = time.perf_counter() - t0
    n = s.buildings + s.parts
    return {
        "buildings": s.buildings,
        "parts": s.parts,
        "surfaces": s.surfaces,
        "seconds": round(dt, 2),
        "buildings_per_s": round(n / dt, 1),
        "top_level_buildings_per_s": round(s.buildings / dt, 1),
        "surfaces_per_s": round(s.surfaces / dt, 1),
        "mb_per_s": round(path.stat().st_size / 1e6 / dt, 2),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "reader_process_peak_rss_mb": None
        if s.reader_peak_rss_mb is None
        else round(s.reader_peak_rss_mb, 1),
        "timings_s": s.timings_s,
        "checks": checks,
    }


def phase_export(url: str, out: Path) -> dict:
    from db.export import export_citygml

    t0 = time.perf_counter()
    s = export_citygml(url, out, model="bench")
    dt = time.perf_counter() - t0
    size = s.path.stat().st_size
    return {
        "top_level_buildings": s.buildings,
        "seconds": round(dt, 2),
        "top_level_buildings_per_s": round(s.buildings / dt, 1),
        "mb_written_per_s": round(size / 1e6 / dt, 2),
        "mb_written": round(size / 1e6, 1),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
    }


def _run_phase(*args: str) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, *args], check=True, capture_output=True, text=True, cwd=str(REPO)
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=87, help="copies of the NRW tile (87 -> ~14,000 buildings)")
    ap.add_argument("--file", type=Path, help="use this CityGML file instead of building one")
    ap.add_argument("--checks", default="fast", choices=("fast", "full", "none"))
    ap.add_argument("--keep", action="store_true", help="keep the bench database and files")
    ap.add_argument("--phase", choices=("import", "export"), help=argparse.SUPPRESS)
    ap.add_argument("--url", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.phase == "import":
        print(json.dumps(phase_import(args.url, args.file, args.checks)))
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
    url = _fresh_database(PG, BENCH_DB)
    try:
        imp = _run_phase("--phase", "import", "--url", url, "--file", str(big), "--checks", args.checks)
        exp = _run_phase("--phase", "export", "--url", url, "--out", str(Path(tmp.name) / "export"))
    finally:
        if not args.keep:
            _drop_database(PG, BENCH_DB)
    result = {
        "input": {
            "file_mb": round(big.stat().st_size / 1e6, 1),
            "copies": None if args.file else args.copies,
            "build_seconds": round(build_s, 1),
        },
        "import": imp,
        "export": exp,
        "bars": {
            "import_buildings_per_s>=1000": imp["buildings_per_s"] >= 1000,
            "import_peak_rss_mb<500": max(imp["peak_rss_mb"], imp["reader_process_peak_rss_mb"] or 0) < 500,
        },
    }
    print(json.dumps(result, indent=1))
    if args.keep:
        print(f"kept: {big} and database {BENCH_DB}", file=sys.stderr)
        tmp.cleanup = lambda: None  # type: ignore[method-assign]


if __name__ == "__main__":
    main()
