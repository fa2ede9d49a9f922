"""What the process pool's fork server imports before it forks workers (`pool.pool_context`):
the job's modules (`workers.job`: the building units' `run_unit` and, through it, the pipeline,
OpenCV and SciPy) and Open3D without its visualisation package (`open3d_light`). Each worker is a
fork of the server, so none imports them again: the units' workers used to import `workers.job`
on their first task (0.9 CPU s each), and Open3D's visualisation package cost 0.55 CPU s per
import. When the job handed the server its frames (`pool.start_pool_server`), the server also
decodes them (`decode_frames`): the workers of the orient and units pools inherit them decoded.

The server starts with the job and does this while the job calibrates in its own process: it
does so in a thread of lower priority (`PRELOAD_NICE`; on Linux a thread has its own nice
value), so that where both want the same core the calibration goes first. The workers fork
from the server's main thread and run at the job's priority.
"""

from __future__ import annotations

import base64
import logging
import os
import pickle
import sys
import threading

from db.sequence_package import FRAME_CACHE_BYTES
from workers.pool import PRELOAD_FRAMES_VAR

_log = logging.getLogger(__name__)

#: how much lower than the job's the priority of the server's imports and decoding is (nice)
PRELOAD_NICE = 5
#: the nice value the preload ran at (None: not known, e.g. not on Linux)
preloaded_at_nice: list[int | None] = [None]


def decode_frames(blob: str | None = None) -> int:
    """Decode every frame of the pickled frame source `blob` (default: `PRELOAD_FRAMES_VAR` of the
    environment; base64) into this process's frame cache (`PackageFrames.raw`), when they all fit
    in it (`FRAME_CACHE_BYTES`, judged by the first frame): else none, as the cache would drop
    the first ones again. Returns the number of frames decoded; never raises (the workers then
    decode what they need, as without)."""
    blob = blob if blob is not None else os.environ.get(PRELOAD_FRAMES_VAR)
    if not blob:
        return 0
    try:
        frames = pickle.loads(base64.b64decode(blob))
        n = len(frames)
        if n == 0 or n * frames.raw(0).nbytes > FRAME_CACHE_BYTES:
            return 0
        for i in range(1, n):
            frames.raw(i)
        return n
    except Exception:  # a frame the job will report itself
        _log.debug("fork server: frames not decoded", exc_info=True)
        return 0


def lower_this_thread(by: int) -> int | None:
    """Raise the nice value of the calling thread only by `by` (Linux: `setpriority` on the
    thread id; elsewhere, where that would name a process, nothing). Returns the thread's nice
    value after, None when unchanged or not known."""
    if sys.platform != "linux":
        return None
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + by)
        return os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return None


def preload() -> None:
    """The server's work before it forks workers: import the job's modules and Open3D, decode
    the frames (`decode_frames`), at `PRELOAD_NICE` below the calling thread's priority."""
    preloaded_at_nice[0] = lower_this_thread(PRELOAD_NICE)
    import workers.job  # noqa: F401  (imported for its side effect: loaded once, in the server)
    from workers.pipeline.geometry.open3d_light import load_open3d

    load_open3d()
    decode_frames()


# in a thread of its own, so that the lower priority ends with it (the workers fork from this one)
_thread = threading.Thread(target=preload, name="citytherm-preload")
_thread.start()
_thread.join()
