"""The service bench's uploads (`bench/service.py`): a city model and a sequence package through
the API (`POST /models`, chunked `PUT /sequences/{id}/parts/{n}` with Content-MD5, commit), and
the upload throughput of random parts with the API's peak RSS before and after.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.service_stack import (
    MiB,
    Stack,
    content_md5,
    expect,
    peak_rss_mb,
    tar_bytes,
    wait_for,
)


# -- uploads --------------------------------------------------------------------------------------
def upload_model(stack: Stack, model: Path) -> tuple[int, dict]:
    import gzip

    t0 = time.perf_counter()
    with stack.client() as c:
        r = expect(
            c.post(
                "/models?name=berlin",
                content=gzip.compress(model.read_bytes()),
                headers={"Content-Type": "application/gml+xml", "Content-Encoding": "gzip"},
            ),
            202,
        )
        mid = int(r.json()["id"])

        def imported() -> dict | None:
            v = c.get(f"/models/{mid}").json()
            return v if v["status"] != "importing" else None

        m = wait_for("the model import", imported)
    if m["status"] != "ready":
        raise RuntimeError(f"model import {m['status']}: {m.get('message')}")
    return mid, {
        "mb": round(model.stat().st_size / 1e6, 2),
        "upload_and_import_s": round(time.perf_counter() - t0, 2),
    }


def upload_package(stack: Stack, pkg: Path, part: int) -> tuple[str, dict]:
    """The package as a .tar in `part`-byte parts, then committed; its id and times."""
    data = tar_bytes(pkg)
    with stack.client() as c:
        sid = expect(c.post("/sequences"), 201).json()["id"]
        t0 = time.perf_counter()
        for n, off in enumerate(range(0, len(data), part), start=1):
            chunk = data[off : off + part]
            md5 = {"Content-MD5": content_md5(chunk)}
            expect(c.put(f"/sequences/{sid}/parts/{n}", content=chunk, headers=md5), 200)
        t1 = time.perf_counter()
        seq = expect(c.post(f"/sequences/{sid}/commit"), 200).json()
        t2 = time.perf_counter()
    return sid, {
        "archive": "tar",
        "mb": round(len(data) / 1e6, 1),
        "parts": -(-len(data) // part),
        "parts_s": round(t1 - t0, 2),
        "commit_s": round(t2 - t1, 2),
        "frames": seq["frames"],
        "platform": seq["platform"],
    }


def upload_throughput(stack: Stack, total: int, part: int) -> dict:
    """`total` random bytes in `part`-byte parts (each made once, in memory), PUT with Content-MD5;
    the upload is then left open (abandoned). MB/s over the PUTs; the API's peak RSS."""
    api = stack.procs["api"].pid
    rss0 = peak_rss_mb(api)
    put_s = 0.0
    sizes = [min(part, total - off) for off in range(0, total, part)]
    t0 = time.perf_counter()
    with stack.client() as c:
        sid = expect(c.post("/sequences"), 201).json()["id"]
        for n, size in enumerate(sizes, start=1):
            chunk = os.urandom(size)
            md5 = content_md5(chunk)
            t = time.perf_counter()
            expect(c.put(f"/sequences/{sid}/parts/{n}", content=chunk, headers={"Content-MD5": md5}), 200)
            put_s += time.perf_counter() - t
        got = expect(c.get(f"/sequences/{sid}"), 200).json()
    wall = time.perf_counter() - t0
    if int(got["bytes"]) != total:
        raise RuntimeError(f"the upload holds {got['bytes']} bytes, not {total}")
    return {
        "mib": total / MiB,
        "part_mib": part / MiB,
        "parts": len(sizes),
        "put_s": round(put_s, 2),
        "mb_per_s": round(total / 1e6 / put_s, 1),
        "wall_s_with_generation": round(wall, 2),
        "api_peak_rss_mb": {"before": rss0, "after": peak_rss_mb(api)},
    }
