"""Frames decoded ahead while the prepare task calibrates (issue 14's speed-up).

In: a job id, its row and its sequence's row in PostGIS, the sequence package on the shared
storage. Out: the package's frames decoded into this worker process's frame cache
(`db.sequence_package.PackageFrames.raw`: the decoded stored values, `FRAME_CACHE_BYTES`, keyed
by file, size and modification time; physical values are one table gather from them); nothing
written anywhere.

Why: the calibrate stage runs in the prepare task alone (about 3.5 CPU s of the ~4 serial CPU s of
the service bench's job) and everything after it (orientation windows, plan, units) starts from
the calibrated priors, so no other task of the job can run meanwhile. Decoding the frames needs no
pose: the prepare task queues `citytherm.prefetch_frames(job id)` before it calibrates, an idle
worker decodes the frames (~6.5 ms CPU each, 640 × 512 px 16-bit PNG) and its window and unit
tasks find them decoded. It stops when the job leaves the calibrate stage (looked up every
`CHECK_EVERY` frames) or its cache is full, and does nothing when it is taken up late (a single
worker takes it after the prepare task: the job is past calibrating) or the job is final. Results
do not change: a cached frame is the decoded file, and a frame the cache lost is decoded again.

Best effort: a prefetch that fails (package gone, database away) logs and returns; the stages read
the frames themselves and report what is wrong. It is never retried.
"""

from __future__ import annotations

import logging
import uuid

from sqlalchemy import text

from db.sequence_package import FRAME_CACHE_BYTES, open_package
from workers import service_storage as storage
from workers.service_process import engine, settings

log = logging.getLogger(__name__)

#: frames decoded between two looks at the job's stage (a look is one small query)
CHECK_EVERY = 8
#: the stage during which decoding ahead helps (the prepare task queues the prefetch as it starts)
STAGE = "calibrate"

_JOB_SQL = (
    "SELECT j.status, j.stage, s.storage_location FROM job j JOIN sequence s ON s.id = j.sequence_id "
    "WHERE j.id = :j"
)


def _job(job_id: uuid.UUID) -> tuple[str, str, str] | None:
    """The job's status and stage and its sequence's storage location (None: no such job)."""
    with engine().connect() as conn:
        row = conn.execute(text(_JOB_SQL), {"j": job_id}).first()
    return None if row is None else (str(row.status), str(row.stage), str(row.storage_location))


def _calibrating(job_id: uuid.UUID) -> bool:
    """True while the job runs its calibrate stage (`STAGE`)."""
    job = _job(job_id)
    return job is not None and job[:2] == ("running", STAGE)


def prefetch_frames(job_id: str) -> str:
    """The prefetch task (module docstring): `decoded <n> frames`, `late` (the job is not
    calibrating), `not a folder` (the sequence is stored as an archive: nothing to share) or
    `failed` (logged)."""
    jid = uuid.UUID(str(job_id))
    try:
        job = _job(jid)
        if job is None or job[:2] != ("running", STAGE):
            return "late"
        package = storage.storage_path(settings().storage_dir, job[2])
        if not package.is_dir():  # an archive would be extracted anew: other files, other cache keys
            return "not a folder"
        n, held = 0, 0
        with open_package(package, check_frames=False) as pkg:
            frames = pkg.frames
            for i in range(len(frames)):
                if i and i % CHECK_EVERY == 0 and not _calibrating(jid):
                    break
                held += frames.raw(i).nbytes  # what the cache keeps (`load` converts from it)
                n += 1
                if held >= FRAME_CACHE_BYTES:
                    break
        return f"decoded {n} frames"
    except Exception as exc:  # a hint only: the stages load what they need themselves
        log.warning("prefetch of job %s's frames failed: %s: %s", jid, type(exc).__name__, exc)
        return "failed"
