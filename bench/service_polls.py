"""Concurrent status pollers for `bench/service.py` (its `poll` figures): threads with one
`httpx.Client` each, asking for one job's status, latency percentiles in milliseconds."""

from __future__ import annotations

import random
import threading
import time

import httpx
import numpy as np

from bench.service_stack import Stack


def pollers(stack: Stack, job: str, n: int, requests: int, interval_s: float) -> dict:
    """`n` threads, each with its own client, `requests` GETs of the job's status each; every
    `interval_s` seconds per poller (0: back to back), the pollers' phases spread at random."""
    lat: list[list[float]] = [[] for _ in range(n)]
    errors: list[str] = []
    barrier = threading.Barrier(n + 1)

    def poll(k: int) -> None:
        rnd = random.Random(k)
        with stack.client(timeout=60) as c:
            c.get("/conformance")  # the connection is made before the clock starts
            barrier.wait()
            start = time.perf_counter() + rnd.uniform(0, interval_s)
            for i in range(requests):
                pause = start + i * interval_s - time.perf_counter()
                if pause > 0:
                    time.sleep(pause)
                t = time.perf_counter()
                try:
                    r = c.get(f"/jobs/{job}")
                    ok = r.status_code == 200
                except httpx.HTTPError as exc:
                    ok, r = False, exc  # type: ignore[assignment]
                lat[k].append(time.perf_counter() - t)
                if not ok:
                    errors.append(str(getattr(r, "status_code", r)))

    threads = [threading.Thread(target=poll, args=(k,), daemon=True) for k in range(n)]
    for t in threads:
        t.start()
    barrier.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    ms = np.array([x for per in lat for x in per]) * 1000.0
    return {
        "pollers": n,
        "requests_each": requests,
        "interval_s": interval_s,
        "requests": int(ms.size),
        "errors": len(errors),
        "wall_s": round(wall, 2),
        "requests_per_s": round(ms.size / wall, 1),
        "p50_ms": round(float(np.percentile(ms, 50)), 1),
        "p95_ms": round(float(np.percentile(ms, 95)), 1),
        "p99_ms": round(float(np.percentile(ms, 99)), 1),
        "max_ms": round(float(ms.max()), 1),
    }
