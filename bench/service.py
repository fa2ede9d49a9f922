"""Service bench (issue 14): a texturing job through the HTTP API and the Celery workers against
the same job in one process, status polling under load, and upload throughput.

A private stack is started as `tests/integration/test_service_e2e.py` starts it: PostgreSQL +
PostGIS (`initdb` into a temporary folder) and `redis-server` on free loopback ports, the API
(`citytherm serve`) and workers (`citytherm worker --concurrency 1`, the first with `--beat`) as
subprocesses with the product's settings (only the database, broker, storage and SRID are set).
Everything is stopped and removed at the end, also after an error.

The scene: a synthetic drive past the bundled Berlin LoD2 model (`synthesize` with the default
GNSS/INS error model, `write_synthetic_package`), by default 100 frames 0.3 s apart around a
cluster of 8 buildings, which the plan turns into ~20-25 building units. Prints one JSON document:

1. `jobs`: the job submitted over HTTP (`POST /processes/texture/execution`, `Prefer:
   respond-async`), polled (`GET /jobs/{id}`) until successful and its results listed (`GET
   /jobs/{id}/results`): wall time from submission with 1 worker process (`one_worker_s`) and with
   2 (`two_workers_s`), `speedup` (bar >= 1.6); the same job by `citytherm run` in this process
   (`workers.run.run_job`, the same `RunOptions`, workers=1): `citytherm_run_s`, and
   `service_overhead` = one_worker_s / citytherm_run_s - 1 (bar <= 0.15), and the same in CPU
   seconds (`service_overhead_cpu`: the stack's processes against `citytherm run`'s, which the
   machine's other load skews less). `citytherm run` and the 1-worker job alternate `--repeat`
   times (default 2), then the 2-worker job runs as often; each figure is the fastest of its
   samples (all are in `samples`). Per job:
   the stage timings the job recorded (`job.timings_s`), its units, a timeline from the rows'
   timestamps (queued, prepare, units, finish), the units' own stage timings, the CPU seconds of
   the API, the workers, PostgreSQL and Redis, also per stage as the polls saw it
   (`by_stage_seen`, with the cores busy on average). The workers are warmed up first
   (`warm_up`: small jobs, so that each pool process has imported Open3D and cv2, which the
   pipeline imports on first use, as long-running workers have; `--cold` skips that), and
   `speedup_bound_units_halved` is the 1-worker job with its units phase halved (Amdahl). Per job
   `timeline` (`bench/service_timeline.py`): which worker process ran which task when (from the
   workers' `task-span` / `window-span` log lines), drawn one row per process, and the speed-up
   its tasks' CPU seconds allow on 2 workers (`speedup_from_cpu`: less skewed by other load).
2. `poll`: `GET /jobs/{id}` latency with 50 concurrent pollers (threads, one `httpx.Client` each,
   40 requests each) while a job runs on 2 workers: `paced` (each poller asks every
   `--poll-interval` s, default 1 s, as a polling client does; bar p95 < 50 ms), then `unpaced`
   (no pause: the API's capacity, where latency is mostly queueing: concurrency / throughput);
   with the API's CPU per request.
3. `upload`: a 500 MiB sequence upload in 8 MiB parts over loopback (`PUT
   /sequences/{id}/parts/{n}` with Content-MD5; random bytes made once per part, then abandoned):
   MB/s over the PUTs, and the API process's peak RSS (`VmHWM`) before and after (streamed: it
   stays far below the upload). The real package's upload and commit time are in `scene`.
4. `bars` and `machine` (cpu count, load averages: the machine may be shared, e.g. with CI).

Usage: `python bench/service.py [--frames 100] [--buildings 8] [--interval 0.3] [--no-refine]
[--repeat 2] [--cold] [--poll-interval 1] [--upload-mb 500] [--worker-threads T] [--keep]` prints
JSON (progress on stderr); ~6-9 minutes on 2 cores. Each worker caps its libraries at
`--worker-threads` threads (`citytherm worker --threads`; default cores // 2, the share of each
of the two workers; 0: uncapped, as before issue 14's caps).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.service_polls import pollers
from bench.service_stack import (
    MiB,
    Stack,
    cpu_delta,
    expect,
    load,
    peak_rss_mb,
    say,
    tree_cpu_s,
    tree_peak_rss_mb,
    wait_for,
)
from bench.service_timeline import timeline
from bench.service_uploads import upload_model, upload_package, upload_throughput


# -- the scene ------------------------------------------------------------------------------------
def make_scene(root: Path, frames: int, buildings: int, interval: float, seed: int) -> tuple[Path, dict]:
    """The synthetic drive past the Berlin model as a package folder; its figures."""
    from db.citygml.reader import read_model
    from db.synth_files import write_synthetic_package
    from workers.pipeline.synth import BUNDLED_MODEL, SynthOptions, synthesize

    t0 = time.perf_counter()
    _, blds = read_model(BUNDLED_MODEL)
    opts = SynthOptions(n_frames=frames, seed=seed, buildings=buildings, frame_interval_s=interval,
                        model_path=str(BUNDLED_MODEL))  # fmt: skip
    res = synthesize(blds, opts)
    pkg = write_synthetic_package(res, root / "seq")
    size = sum(p.stat().st_size for p in pkg.rglob("*") if p.is_file())
    return pkg, {
        "model": BUNDLED_MODEL.name,
        "model_buildings": len(blds),
        "frames": frames,
        "frame_interval_s": interval,
        "drive_m": round(frames * interval * opts.drive.speed_mps, 1),
        "cluster_buildings": len(res.truth.cluster),
        "seed": seed,
        "gnss_ins_errors": opts.errors.enabled,
        "package_mb": round(size / 1e6, 1),
        "synth_and_write_s": round(time.perf_counter() - t0, 1),
    }


# -- jobs -----------------------------------------------------------------------------------------
def submit(c: httpx.Client, inputs: dict) -> tuple[str, float]:
    t0 = time.perf_counter()
    r = expect(c.post("/processes/texture/execution", json={"inputs": inputs},
                      headers={"Prefer": "respond-async"}), 201)  # fmt: skip
    return str(r.json()["jobID"]), t0


def until_results(
    c: httpx.Client, job: str, step_s: float = 0.2, seen: Callable[[dict], None] | None = None
) -> dict:
    """Poll the job until it is successful and its results are listed; its status document.
    `seen` is called with every status document."""

    def done() -> dict | None:
        s = expect(c.get(f"/jobs/{job}"), 200).json()
        if seen is not None:
            seen(s)
        if s["status"] in ("failed", "dismissed"):
            raise RuntimeError(f"job {job} is {s['status']}: {s.get('message')}")
        if s["status"] == "successful" and c.get(f"/jobs/{job}/results").status_code == 200:
            return s
        return None

    return wait_for(f"job {job}", done, step_s=step_s)


def job_figures(stack: Stack, job: str) -> dict:
    """What the job recorded: stage timings, units, and a timeline from the rows' timestamps."""
    [(timings, created, started, finished, written)] = stack.sql(
        "SELECT timings_s, created_at, started_at, finished_at, updated_at FROM job WHERE id = %s", job
    )
    span = "EXTRACT(EPOCH FROM finished_at - started_at)"
    [(n, first, last, busy, longest)] = stack.sql(
        f"SELECT count(*), min(started_at), max(finished_at), sum({span}), max({span}) "
        "FROM job_unit WHERE job_id = %s",
        job,
    )
    states = dict(stack.sql("SELECT status, count(*) FROM job_unit WHERE job_id = %s GROUP BY 1", job))
    # what the units' pipeline measured itself (`workers.job.run_unit`: the result's timings)
    by_stage = dict(stack.sql(
        "SELECT k, sum(v::float) FROM job_unit, jsonb_each_text(timings_s) AS t(k, v) WHERE job_id = %s "
        "GROUP BY k", job,
    ))  # fmt: skip
    pipeline = sum(by_stage.values())
    return {
        "units": int(n),
        "units_by_status": {k: int(v) for k, v in states.items()},
        "timings_s": {k: round(float(v), 2) for k, v in (timings or {}).items()},
        "timeline_s": {
            "queued": round((started - created).total_seconds(), 2),
            "prepare_until_first_unit": round((first - started).total_seconds(), 2),
            "units_span": round((last - first).total_seconds(), 2),
            "finish": round((written - finished).total_seconds(), 2),
            "units_busy_sum": round(float(busy or 0), 2),
            "units_pipeline_sum": round(float(pipeline or 0), 2),
            "units_outside_pipeline_sum": round(float(busy or 0) - float(pipeline or 0), 2),
            "longest_unit": round(float(longest or 0), 2),
        },
        "units_pipeline_by_stage_s": {k: round(float(v), 2) for k, v in sorted(by_stage.items())},
    }


class StageCpu:
    """CPU seconds of the stack's processes per job stage as the status shows it (`prepare`: the
    stages before the units), sampled on every stage change and at most once a second."""

    def __init__(self, stack: Stack) -> None:
        self.stack = stack
        self.last = (time.perf_counter(), "submitted", tree_cpu_s(stack.pids()))
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))

    def sample(self, status: dict | None) -> None:
        stage = "done" if status is None else status["stage"]
        stage = "prepare" if stage in ("accepted", "ingest", "calibrate", "orient", "plan") else stage
        t0, stage0, cpu0 = self.last
        now = time.perf_counter()
        if stage == stage0 and now - t0 < 1.0:
            return
        cpu = tree_cpu_s(self.stack.pids())
        self.wall[stage0] += now - t0
        for k, v in cpu.items():
            self.cpu[stage0][k] += v - cpu0.get(k, 0.0)
        self.last = (now, stage, cpu)

    def figures(self) -> dict:
        return {
            stage: {
                "wall_s": round(wall, 1),
                "cpu_s": {k: round(v, 1) for k, v in self.cpu[stage].items()},
                "cores_busy": round(sum(self.cpu[stage].values()) / wall, 2) if wall else None,
            }
            for stage, wall in self.wall.items()
        }


def finish_logged(stack: Stack, job: str, patience_s: float = 30.0) -> dict[str, str]:
    """The workers' logs once the finish task of `job` has logged its `task-span` line: the
    results are served from the finish's commit on, a moment before its task ends and logs (at
    most `patience_s` s; then the logs as they are)."""

    def logs() -> dict[str, str]:
        return {name: stack.log(name) for name in stack.procs if name.startswith("w")}

    def finished(text: str) -> bool:
        return any("task-span" in ln and "finish_job" in ln and job in ln for ln in text.splitlines())

    try:
        wait_for(f"the finish of {job} in the logs", lambda: any(map(finished, logs().values())),
                 patience_s=patience_s, step_s=0.1)  # fmt: skip
    except TimeoutError:
        say(f"no finish task-span for job {job} in the worker logs")
    return logs()


def service_job(stack: Stack, inputs: dict) -> dict:
    """Submit, poll until results are listed; wall time from submission, the job's figures, CPU
    (whole job and per stage)."""
    cpu0 = tree_cpu_s(stack.pids())
    load0 = load()
    stages = StageCpu(stack)
    with stack.client() as c:
        t_unix = time.time()
        job, t0 = submit(c, inputs)
        status = until_results(c, job, seen=stages.sample)
        wall = time.perf_counter() - t0
    stages.sample(None)
    cpu = cpu_delta(cpu0, tree_cpu_s(stack.pids()))
    logs = finish_logged(stack, job)
    return {
        "timeline": timeline(logs, job, t_unix, workers=2),
        "job": job,
        "wall_s": round(wall, 2),
        "progress": status["progress"],
        **job_figures(stack, job),
        "cpu_s": cpu,
        "cpu_s_total": round(sum(cpu.values()), 1),
        "by_stage_seen": stages.figures(),
        "load_avg_1min": {"before": load0, "after": load()},
    }


def citytherm_run(model: Path, pkg: Path, out: Path, options: Any) -> dict:
    """`workers.run.run_job` in this process (the `citytherm run` path)."""
    from workers.run import run_job

    load0 = load()
    c0, t0 = time.process_time(), time.perf_counter()
    s = run_job(model, pkg, out, options)
    wall = time.perf_counter() - t0
    by_stage: dict[str, float] = defaultdict(float)
    for r in s.results:
        for k, v in r.timings_s.items():
            by_stage[k] += v
    return {
        "wall_s": round(wall, 2),
        "units": len(s.results) + len(s.failures),
        "failed": len(s.failures),
        "timings_s": {k: round(v, 2) for k, v in s.timings_s.items()},
        "units_pipeline_sum": round(sum(by_stage.values()), 2),
        "units_pipeline_by_stage_s": {k: round(v, 2) for k, v in sorted(by_stage.items())},
        "units_frames": sum(s.units_frames.values()),
        "cpu_s": round(time.process_time() - c0, 1),
        "load_avg_1min": {"before": load0, "after": load()},
        "_frames_by_building": dict(s.units_frames),
    }


def warm_up(stack: Stack, base: dict, buildings: list[str], worker: str) -> dict:
    """Small jobs (no refinement, a few buildings) until `worker` has run a unit: every pool
    process of the stack has then imported what the pipeline imports on first use (Open3D, cv2),
    as a service's long-running workers have; `citytherm run` runs in this process, which has
    (the synthetic scene was rendered with Open3D). Returns the jobs and their time."""
    t0 = time.perf_counter()
    n = 0
    with stack.client() as c:
        while n < 5 and (n == 0 or "run_unit" not in stack.log(worker)):
            job, _ = submit(c, {**base, "refine": False, "buildings": buildings})
            until_results(c, job)
            n += 1
    return {"jobs": n, "s": round(time.perf_counter() - t0, 1), "unit_ran_on_" + worker: "run_unit" in
            stack.log(worker)}  # fmt: skip


# -- pollers --------------------------------------------------------------------------------------
def poll_under_load(stack: Stack, inputs: dict, n: int, requests: int, interval_s: float) -> dict:
    """A job on the workers; once it runs, paced pollers, then unpaced ones; then its end."""
    out: dict = {}
    with stack.client() as c:
        job, t0 = submit(c, inputs)
        wait_for("the job to run", lambda: c.get(f"/jobs/{job}").json()["status"] == "running")
        for phase, every in (("paced", interval_s), ("unpaced", 0.0)):
            s0 = c.get(f"/jobs/{job}").json()
            load0, cpu0 = load(), tree_cpu_s(stack.pids())
            out[phase] = pollers(stack, job, n, requests, every)
            cpu = cpu_delta(cpu0, tree_cpu_s(stack.pids()))
            s1 = c.get(f"/jobs/{job}").json()
            out[phase]["cpu_s"] = cpu
            out[phase]["api_cpu_ms_per_request"] = round(1000 * cpu["api"] / out[phase]["requests"], 2)
            out[phase]["job_during"] = {
                "from": f"{s0['status']}/{s0['stage']}",
                "to": f"{s1['status']}/{s1['stage']}",
                "ran_throughout": s1["status"] == "running",
            }
            out[phase]["load_avg_1min"] = {"before": load0, "after": load()}
        until_results(c, job)
        out["job_wall_s_with_pollers"] = round(time.perf_counter() - t0, 2)
    return out


# -- main -----------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--buildings", type=int, default=8, help="the drive's cluster (more buildings are seen)")
    ap.add_argument("--interval", type=float, default=0.3, help="seconds between frames (8 m/s drive)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-refine", dest="refine", action="store_false", help="keep the GNSS/INS poses")
    ap.add_argument("--pollers", type=int, default=50)
    ap.add_argument("--poll-requests", type=int, default=40)
    ap.add_argument("--poll-interval", type=float, default=1.0, help="seconds between a poller's requests")
    ap.add_argument("--upload-mb", type=int, default=500, help="MiB of the upload throughput test")
    ap.add_argument("--part-mb", type=int, default=8, help="MiB per part")
    ap.add_argument("--repeat", type=int, default=2, help="samples of each job (citytherm run, 1, 2 workers)")
    ap.add_argument("--cold", dest="warm", action="store_false",
                    help="no warm-up jobs: the measured jobs meet freshly started workers")  # fmt: skip
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder (logs, storage)")
    ap.add_argument("--worker-threads", type=int, default=max(1, (os.cpu_count() or 1) // 2),
                    help="library threads per worker process (default: cores // 2, so that the two "
                    "workers do not oversubscribe the cores; 0: no cap)")  # fmt: skip
    a = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up on SIGTERM too
    if a.worker_threads > 0:  # `citytherm run` here with the workers' caps of OpenCV and Open3D
        from workers.pool import THREADS_VAR, cap_library_threads

        os.environ[THREADS_VAR] = str(a.worker_threads)
        cap_library_threads()

    from services.api.schemas import TextureInputs
    from workers.pipeline.synth import BUNDLED_MODEL

    machine = {"cpu_count": os.cpu_count(), "load_avg_before": [round(x, 2) for x in os.getloadavg()]}
    root = Path(tempfile.mkdtemp(prefix="citytherm-bench-service-"))
    stack = Stack(root)
    out: dict = {"bench": "service"}
    try:
        say("synthesizing the drive")
        pkg, scene = make_scene(root, a.frames, a.buildings, a.interval, a.seed)
        out["scene"] = scene
        # the job's inputs over HTTP; citytherm run gets the RunOptions the API builds from them
        job_inputs = {"refine": a.refine}
        any_ids = {"model": 1, "sequence": "00000000-0000-0000-0000-000000000000"}
        options = TextureInputs(**any_ids, **job_inputs).run_options()
        out["options"] = {
            "refine": options.refine,
            "calibrate": options.calibrate,
            "orient": options.orient,
            "resolution_px_per_m": options.resolution_px_per_m,
            "workers": options.workers,
            "worker_threads": a.worker_threads,
        }

        say("starting the stack (PostgreSQL, Redis, API, worker w1 with beat)")
        stack.up()
        stack.start_worker("w1", beat=True, threads=a.worker_threads)
        mid, out["model_upload"] = upload_model(stack, BUNDLED_MODEL)
        sid, out["scene"]["sequence_upload"] = upload_package(stack, pkg, a.part_mb * MiB)
        inputs = {"model": mid, "sequence": sid, **job_inputs}

        say(f"upload throughput: {a.upload_mb} MiB in {a.part_mb} MiB parts")
        out["upload"] = upload_throughput(stack, a.upload_mb * MiB, a.part_mb * MiB)

        # `citytherm run` and the 1-worker job alternate (--repeat pairs), so that they see much the
        # same machine load; each figure is the fastest of its samples (other load only adds time)
        runs: list[dict] = []
        ones: list[dict] = []
        warm: dict = {}
        for i in range(a.repeat):
            say(f"citytherm run (in process, workers=1; the stack idles) {i + 1}/{a.repeat}")
            runs.append(citytherm_run(BUNDLED_MODEL, pkg, root / f"run-results-{i}", options))
            frames_of = runs[-1].pop("_frames_by_building")
            if a.warm and not warm:
                small = sorted(frames_of, key=lambda b: frames_of[b])[:4]  # the cheapest units
                warm["w1"] = warm_up(stack, inputs, small, "w1")
            say(f"  {runs[-1]['wall_s']} s; job with 1 worker {i + 1}/{a.repeat}")
            ones.append(service_job(stack, inputs))
            say(f"  {ones[-1]['wall_s']} s")
        run = min(runs, key=lambda r: r["wall_s"])
        one = min(ones, key=lambda r: r["wall_s"])
        out["citytherm_run"] = run
        say("starting worker w2")
        stack.start_worker("w2", beat=False, threads=a.worker_threads)
        if a.warm:
            warm["w2"] = warm_up(stack, inputs, small, "w2")
        out["warm_up"] = warm or None
        twos: list[dict] = []  # as many samples as of the 1-worker job: the fastest of each
        for i in range(a.repeat):
            say(f"job with 2 workers {i + 1}/{a.repeat}")
            twos.append(service_job(stack, inputs))
            say(f"  {twos[-1]['wall_s']} s")
        two = min(twos, key=lambda r: r["wall_s"])
        out["jobs"] = {
            "one_worker_s": one["wall_s"],
            "two_workers_s": two["wall_s"],
            "citytherm_run_s": run["wall_s"],
            "samples": {
                "citytherm_run_s": [r["wall_s"] for r in runs],
                "one_worker_s": [r["wall_s"] for r in ones],
                "two_workers_s": [r["wall_s"] for r in twos],
                "citytherm_run_cpu_s": [r["cpu_s"] for r in runs],
                "one_worker_cpu_s": [r["cpu_s_total"] for r in ones],
            },
            "one_worker": one,
            "two_workers": two,
        }
        out["speedup"] = round(one["wall_s"] / two["wall_s"], 3)
        out["speedup_from_cpu"] = {k: j["timeline"]["speedup_from_cpu"] for k, j in (("one_worker", one),
                                   ("two_workers", two))}  # fmt: skip
        # Amdahl: the 1-worker job with its units phase halved and everything else as it was
        half = one["wall_s"] - one["timeline_s"]["units_span"] / 2
        out["speedup_bound_units_halved"] = round(one["wall_s"] / half, 3)
        out["service_overhead"] = round(one["wall_s"] / run["wall_s"] - 1.0, 3)
        # the same in CPU seconds (API, workers, PostgreSQL, Redis against this process): what the
        # service adds, whatever share of the cores the machine's other load leaves
        cpu_one = min(r["cpu_s_total"] for r in ones)
        out["service_overhead_cpu"] = round(cpu_one / min(r["cpu_s"] for r in runs) - 1.0, 3)

        say(f"{a.pollers} pollers while a job runs on 2 workers")
        out["poll"] = poll_under_load(stack, inputs, a.pollers, a.poll_requests, a.poll_interval)
        out["api_peak_rss_mb_end"] = peak_rss_mb(stack.procs["api"].pid)
        out["peak_rss_mb_largest_process"] = tree_peak_rss_mb(stack.pids())
    finally:
        say("stopping the stack")
        stack.close()
        if a.keep:
            say(f"kept {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)
    machine["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    out["machine"] = machine
    out["bars"] = {
        "speedup>=1.6": out["speedup"] >= 1.6,
        "service_overhead<=0.15": out["service_overhead"] <= 0.15,
        "poll_p95_ms<50 (paced)": out["poll"]["paced"]["p95_ms"] < 50,
        "units_equal_citytherm_run": out["jobs"]["one_worker"]["units"]
        == run["units"]
        == out["jobs"]["two_workers"]["units"],
    }
    print(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
