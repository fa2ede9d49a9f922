"""The service bench's job timeline (`bench/service.py`): which worker process ran which task of a
job when, from the `task-span` lines of the workers (`workers.tasks`) and the `window-span` lines
of the orientation windows (`workers.service_windows`) in their logs, a critical-path estimate
from the tasks' CPU seconds, and the parts of the finish (its `finish-parts` line).

Times are seconds from the job's submission (wall clock of this machine); CPU seconds are those of
the worker process over the task (`time.process_time`, all its threads). On a shared machine the
wall spans stretch with the other load, the CPU seconds much less: the estimate
(`critical_path_cpu`) schedules the measured CPU seconds of the job's tasks on n idle workers as
the service runs them (prepare's own part serial, its windows over the workers, the units in the
order they started, each to the first free worker, then finish; the frames decoded ahead by a
`prefetch` task beside the prepare task on another worker, or after it on one) and gives the
speed-up those CPU seconds allow.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterable
from typing import Any

SHORT = {"citytherm.prepare_job": "prepare", "citytherm.orient_window": "window-task",
         "citytherm.run_unit": "unit", "citytherm.finish_job": "finish",
         "citytherm.prefetch_frames": "prefetch"}  # fmt: skip
#: the characters of `draw` per kind of span
MARK = {"prepare": "P", "window": "W", "unit": "U", "finish": "F", "window-task": "w", "prefetch": "d"}


def spans(log: str) -> list[dict[str, Any]]:
    """Every `task-span` and `window-span` record of one worker log (`kind`: `task` or `window`)."""
    out = []
    for line in log.splitlines():
        for kind in ("task", "window"):
            tag = f"{kind}-span "
            if tag in line:
                try:
                    rec = json.loads(line.split(tag, 1)[1])
                except ValueError:
                    continue
                out.append({"kind": kind, **rec})
    return out


def finish_parts(logs: dict[str, str], job: str) -> list[dict[str, Any]]:
    """The `finish-parts` records of job `job` in the workers' `logs` (`service_job.finish_job`:
    wall seconds of gathering the units' results, writing the folder and zipping it; how many
    results the units kept and how many were loaded from PostGIS; its wall and CPU seconds)."""
    out = []
    for worker, text in logs.items():
        for line in text.splitlines():
            if "finish-parts " in line:
                try:
                    rec = json.loads(line.split("finish-parts ", 1)[1])
                except ValueError:
                    continue
                if rec.get("job") == job:
                    out.append({"worker": worker, **rec})
    return out


def job_spans(logs: dict[str, str], job: str, t_submit: float) -> list[dict[str, Any]]:
    """The spans of job `job` in the workers' `logs` (worker name -> log text), start order, times
    from `t_submit` (Unix time of the submission)."""
    out = []
    for worker, text in logs.items():
        for s in spans(text):
            if s["kind"] == "task":
                if not s["args"] or s["args"][0] != job or s["task"] not in SHORT:
                    continue
                what = SHORT[s["task"]]
                label = s["args"][1] if len(s["args"]) > 1 else ""
            else:
                if s["job"] != job:
                    continue
                what, label = "window", str(s["window"])
            out.append({
                "worker": worker, "pid": s["pid"], "what": what, "label": label,
                "t0": round(s["start"] - t_submit, 2), "t1": round(s["end"] - t_submit, 2),
                "cpu_s": round(float(s["cpu_s"]), 2), "result": s.get("result"),
            })  # fmt: skip
    return sorted(out, key=lambda s: (s["t0"], s["t1"]))


def makespan(costs: Iterable[float], n: int) -> float:
    """Each cost in order to the first free of `n` workers (list scheduling): the end of the last."""
    free = [0.0] * max(1, n)
    for c in costs:
        heapq.heappush(free, heapq.heappop(free) + float(c))
    return max(free)


def critical_path_cpu(sp: list[dict[str, Any]], n: int) -> dict[str, float]:
    """The job's CPU seconds scheduled on `n` workers (module docstring): `serial` (prepare without
    its windows, finish), `windows` and `units` (their makespans), `prefetch` (frames decoded
    ahead: on 1 worker all of it adds, on more only what outlasts the prepare's serial part),
    `total`."""
    prepare = [s for s in sp if s["what"] == "prepare" and str(s["result"]).startswith("queued")]
    windows = [s for s in sp if s["what"] == "window"]
    inside = [w for w in windows for p in prepare if w["pid"] == p["pid"] and p["t0"] <= w["t0"] <= p["t1"]]
    own = sum(w["cpu_s"] for w in inside)
    serial = sum(p["cpu_s"] for p in prepare) - own
    ahead = sum(s["cpu_s"] for s in sp if s["what"] == "prefetch")
    ahead = ahead if n <= 1 else max(0.0, ahead - serial)
    serial += sum(s["cpu_s"] for s in sp if s["what"] == "finish")
    units = [s["cpu_s"] for s in sp if s["what"] == "unit" and s["result"] == "stored"]
    w = makespan(sorted((x["cpu_s"] for x in windows), reverse=True), n)
    u = makespan(units, n)
    return {"serial": round(serial, 2), "windows": round(w, 2), "units": round(u, 2),
            "prefetch": round(ahead, 2), "total": round(serial + w + u + ahead, 2)}  # fmt: skip


def draw(sp: list[dict[str, Any]], step_s: float = 0.5) -> dict[str, str]:
    """One text row per worker process: a character per `step_s` seconds from the submission,
    `MARK` of the span running then (a window inside the prepare task shows as W), `.` idle."""
    rows: dict[str, list[str]] = {}
    end = max((s["t1"] for s in sp), default=0.0)
    for s in sorted(sp, key=lambda s: s["what"] == "window"):  # windows drawn over their task
        key = f"{s['worker']}/{s['pid']}"
        row = rows.setdefault(key, ["."] * (int(end / step_s) + 1))
        for k in range(int(s["t0"] / step_s), int(s["t1"] / step_s) + 1):
            row[k] = MARK[s["what"]] if s["what"] != "window-task" or row[k] == "." else row[k]
    return {k: "".join(v) for k, v in sorted(rows.items())}


def timeline(logs: dict[str, str], job: str, t_submit: float, workers: int) -> dict[str, Any]:
    """The job's spans, their drawing, busy seconds per worker process and the critical-path
    estimate on 1 worker and on `workers` (module docstring)."""
    sp = job_spans(logs, job, t_submit)
    busy: dict[str, float] = {}
    for s in sp:
        if s["what"] != "window":  # inside a task span
            key = f"{s['worker']}/{s['pid']}"
            busy[key] = round(busy.get(key, 0.0) + s["t1"] - s["t0"], 2)
    one, many = critical_path_cpu(sp, 1), critical_path_cpu(sp, workers)
    return {
        "spans": sp,
        "drawing_step_s": 0.5,
        "drawing": draw(sp),
        "busy_wall_s": busy,
        "critical_path_cpu_s": {"1": one, str(workers): many},
        "finish_parts": finish_parts(logs, job),
        "speedup_from_cpu": round(one["total"] / many["total"], 3) if many["total"] else None,
    }
