"""CityGML I/O benchmark: streaming read and CityGML 2.0 write of a ~200 MB model.

Builds a large input by replicating the NRW LoD2 tile (`tests/data/nrw-tile-5659-...gml`,
109 buildings + 55 parts per copy) with fresh ids (`<id>_c<k>`) and coordinates shifted by whole
kilometres (copy k at +1000·(k mod 10) m east, +1000·(k // 10) m north), then measures, each phase
in its own subprocess so that peak RSS figures are separate:

- read: `iter_buildings` over the whole file: MB/s, buildings/s (top-level, and with parts),
  polygons/s, peak RSS; also MB per CPU second and the load average, since the machine is shared
  (wall-clock figures drop when other processes compete for the two cores);
- write: the same buildings streamed into `write_citygml` (time spent reading subtracted): MB/s
  written, buildings/s, peak RSS.

Bars (issue 3): read >= 15 MB/s and >= 1,000 buildings/s, peak RSS < 500 MB.

Usage: `python bench/citygml_io.py [--copies 87] [--file PATH] [--keep]` prints JSON.
`make_replicated_model(src, dst, copies)` is reused by the database benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
NRW = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"

_MEMBER = re.compile(rb"<core:cityObjectMember>.*?</core:cityObjectMember>\s*", re.S)
_ID = re.compile(rb'(gml:id="|xlink:href="#)([^"]+)"')
_COORDS = re.compile(rb"(<gml:(?:posList|pos|lowerCorner|upperCorner)[^>]*>)([^<]*)(<)")


def _shift_block(block: bytes, k: int, dx: float, dy: float) -> bytes:
    """One copy of a cityObjectMember: ids suffixed `_c<k>`, x/y shifted (3D coordinates)."""
    suffix = f"_c{k}".encode()
    block = _ID.sub(lambda m: m.group(1) + m.group(2) + suffix + b'"', block)

    def coords(m: re.Match[bytes]) -> bytes:
        v = np.array(m.group(2).split(), dtype=np.float64).reshape(-1, 3)
        v[:, 0] += dx
        v[:, 1] += dy
        text = " ".join(f"{a:.3f} {b:.3f} {c:.3f}" for a, b, c in v.tolist())
        return m.group(1) + text.encode() + m.group(3)

    return _COORDS.sub(coords, block)


def make_replicated_model(src: Path | str, dst: Path | str, copies: int) -> Path:
    """Write `copies` shifted copies of the buildings of `src` (a CityGML file whose members are
    `<core:cityObjectMember>`, like the NRW tile) into `dst`; ids stay unique. Returns `dst`."""
    src, dst = Path(src), Path(dst)
    data = src.read_bytes()
    members = list(_MEMBER.finditer(data))
    if not members:
        raise ValueError(f"{src}: no <core:cityObjectMember> found")
    head = data[: members[0].start()]
    tail = data[members[-1].end() :]
    body = data[members[0].start() : members[-1].end()]
    with open(dst, "wb") as f:
        f.write(head)
        for k in range(copies):
            f.write(_shift_block(body, k, 1000.0 * (k % 10), 1000.0 * (k // 10)))
        f.write(tail)
    return dst


def _peak_rss_mb() -> float:
    """Peak resident set of this process (MB): `VmHWM` of /proc (per address space, so not
    inherited from the parent through fork/exec, unlike `ru_maxrss`), else `ru_maxrss`."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _phase_read(path: Path) -> dict:
    from db.citygml import iter_buildings

    t0, c0 = time.perf_counter(), time.process_time()
    n_b = n_all = n_poly = 0
    for b in iter_buildings(path):
        n_b += 1
        for x in b.iter_buildings():
            n_all += 1
            n_poly += len(x.polygons)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    mb = path.stat().st_size / 1e6
    return {
        "file_mb": round(mb, 1),
        "seconds": round(dt, 2),
        "cpu_seconds": round(cpu, 2),
        "mb_per_s": round(mb / dt, 1),
        "mb_per_cpu_s": round(mb / cpu, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "buildings": n_b,
        "buildings_and_parts": n_all,
        "polygons": n_poly,
        "buildings_per_s": round(n_b / dt),
        "buildings_and_parts_per_s": round(n_all / dt),
        "polygons_per_s": round(n_poly / dt),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
    }


def _phase_write(path: Path, out: Path) -> dict:
    from db.citygml import open_model, write_citygml

    header, buildings, late = open_model(path)
    read_time = 0.0
    n = 0

    def timed():
        nonlocal read_time, n
        it = iter(buildings)
        while True:
            t = time.perf_counter()
            try:
                b = next(it)
            except StopIteration:
                read_time += time.perf_counter() - t
                return
            read_time += time.perf_counter() - t
            n += 1
            yield b

    t0 = time.perf_counter()
    write_citygml(
        out,
        timed(),
        srs_name=header.srs_name,
        envelope=header.envelope,
        model_appearances=header.appearances,
        trailing_appearances=late,
    )
    total = time.perf_counter() - t0
    dt = total - read_time
    mb = out.stat().st_size / 1e6
    return {
        "out_mb": round(mb, 1),
        "write_seconds": round(dt, 2),
        "read_seconds": round(read_time, 2),
        "mb_per_s": round(mb / dt, 1),
        "buildings_per_s": round(n / dt),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
    }


def _run_phase(*args: str) -> dict:
    res = subprocess.run(
        [sys.executable, __file__, "--phase", *args], capture_output=True, text=True, check=True, cwd=REPO
    )
    return json.loads(res.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=87, help="copies of the NRW tile (87 -> ~200 MB)")
    ap.add_argument("--file", type=Path, help="where to build the large model (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the generated files")
    ap.add_argument("--phase", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.phase:
        kind, *paths = args.phase
        if kind == "read":
            print(json.dumps(_phase_read(Path(paths[0]))))
        else:
            print(json.dumps(_phase_write(Path(paths[0]), Path(paths[1]))))
        return
    tmp = tempfile.TemporaryDirectory(prefix="citygml-bench-")
    big = args.file or Path(tmp.name) / "nrw-replicated.gml"
    t0 = time.perf_counter()
    make_replicated_model(NRW, big, args.copies)
    build_s = time.perf_counter() - t0
    out = big.with_name(big.stem + "-written.gml")
    read = _run_phase("read", str(big))
    write = _run_phase("write", str(big), str(out))
    bars = {
        "read_mb_per_s>=15": read["mb_per_s"] >= 15,
        "read_buildings_per_s>=1000": read["buildings_per_s"] >= 1000,
        "read_peak_rss_mb<500": read["peak_rss_mb"] < 500,
    }
    print(json.dumps({"copies": args.copies, "build_seconds": round(build_s, 1), "read": read,
                      "write": write, "bars": bars}, indent=2))  # fmt: skip
    if not args.keep:
        out.unlink(missing_ok=True)
        if args.file is None:
            tmp.cleanup()


if __name__ == "__main__":
    main()
