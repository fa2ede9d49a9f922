"""The orient stage's windows as Celery tasks on real workers (`workers.service_windows`): window
tasks queued to two `citytherm worker` processes, which are SIGKILLed while one of them holds a
window; the prepare side (`celery_window_map`, run here) then runs what is left, and the merged
orientation equals the serial one (a 24-frame synthetic drive in 2 windows of 16 frames)."""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from db import jobs
from db.importer import import_citygml
from tests.unit.orientation_scenes import perturb
from workers import service_job
from workers import service_windows as sw
from workers.pipeline.geometry.manifest import Accuracy, MemoryFrames
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.sequence import (
    SequenceOrientationOptions,
    merge_windows,
    orient_sequence,
    orient_window,
    plan_windows,
)
from workers.service_storage import write_pickle

N = 24
PATIENCE_S = 300.0
MODEL = Path(__file__).resolve().parents[1] / "data" / "bavaria-1-building-citygml2-lod2.gml"


@pytest.fixture(scope="module")
def drive() -> tuple:
    from workers.pipeline.synth import SynthOptions, procedural_block, synthesize

    opts = SynthOptions(platform="drive", n_frames=N, seed=1, buildings=2)
    res = synthesize(procedural_block(6, seed=1), opts)
    rng = np.random.default_rng(5)
    common_m, common_deg = np.array([0.4, -0.3, 0.3]), np.array([0.3, -0.4, 0.2])
    prior = {i: perturb(T, common_m + rng.normal(0, 0.2, 3), common_deg + rng.normal(0, 0.15, 3))
             for i, T in enumerate(res.truth.poses)}  # fmt: skip
    times = {i: f.time for i, f in enumerate(res.manifest.frames)}
    acc = Accuracy(position_m=np.full(3, 0.5), attitude_deg=np.full(3, 0.5))
    frames = MemoryFrames({i: res.frames.load(i) for i in range(N)})
    windows = SequenceOrientationOptions(window_frames=16, overlap_frames=8)
    return res.manifest.camera, RayCaster(res.mesh), list(range(N)), frames, prior, times, acc, windows


def _job(db_engine: Any) -> uuid.UUID:
    model = import_citygml(db_engine, MODEL, name=f"windows-{uuid.uuid4().hex[:8]}").model_id
    with Session(db_engine) as s:
        jid = jobs.create_job(s, model_id=model)
        s.commit()
    return jid


def _held(db_engine: Any, jid: uuid.UUID, k: int) -> bool:
    """True while some session holds window k's advisory lock (`pg_locks`, without taking it: a
    bigint key shows as classid = its high and objid = its low 32 bits)."""
    with db_engine.connect() as c:
        name = {"k": f"citytherm-window-{k}:{jid}"}
        key = int(c.execute(text("SELECT hashtext(:k)::bigint"), name).scalar())
        sql = "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND objsubid = 1 AND granted AND "
        sql += "classid::bigint = :hi AND objid::bigint = :lo"
        return bool(c.execute(text(sql), {"hi": (key >> 32) & 0xFFFFFFFF, "lo": key & 0xFFFFFFFF}).scalar())


def test_windows_on_workers_killed_midway_give_the_serial_result(drive, celery_workers, db_engine) -> None:
    celery_workers.ensure()
    service_job.settings.cache_clear()  # this session's storage and database
    serial = orient_sequence(*drive)
    plan = plan_windows(*drive)
    assert len(plan.tasks) == 2
    jid = _job(db_engine)
    for t in plan.tasks:  # what `celery_window_map` does first
        write_pickle(sw._task_path(jid, t.index), t)
        service_job.send("citytherm.orient_window", str(jid), t.index)
    deadline = time.monotonic() + PATIENCE_S
    while not _held(db_engine, jid, 0):  # a worker runs window 0 ...
        assert time.monotonic() < deadline, "no worker took window 0"
        time.sleep(0.05)
    for name in celery_workers.names:  # ... and dies (its connection, and with it the lock, go)
        celery_workers.kill(name)
    try:
        assert not sw._result_path(jid, 0).exists()
        results = list(sw.celery_window_map(jid, poll_s=0.05)(orient_window, plan.tasks))
    finally:
        celery_workers.ensure()
    merged = merge_windows(plan, results)
    assert merged.oriented == serial.oriented and merged.blocks == serial.blocks
    for f in serial.poses:
        np.testing.assert_allclose(merged.poses[f].center, serial.poses[f].center, rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            merged.poses[f].R_world_from_cam, serial.poses[f].R_world_from_cam, rtol=0, atol=1e-9
        )
    np.testing.assert_array_equal(merged.tracks.frame, serial.tracks.frame)
    assert not sw.windows_dir(jid).exists()
