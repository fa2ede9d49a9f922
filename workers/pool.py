"""The process pool context of the in-process job (`citytherm run --workers N`): the orient stage's
windows (`pool_map`, `workers.job.orient`), the building units (`workers.run.run_units`) and the
split-half check (`workers.split_half`) share it."""

from __future__ import annotations

import base64
import multiprocessing
import multiprocessing.context
import os
import pickle
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import forkserver
from typing import Any

#: thread-pool sizes of numerical libraries read from the environment when they load (OpenMP,
#: OpenBLAS, MKL, numexpr, OpenCV's pool); Open3D's TBB has none (`cap_library_threads`)
LIBRARY_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
)
#: the cap itself, for `cap_library_threads` in processes that start from this environment
THREADS_VAR = "CITYTHERM_LIBRARY_THREADS"


def library_thread_env(threads: int) -> dict[str, str]:
    """The environment that caps the numerical libraries of a process started with it at
    `threads` threads each (`threads >= 1`)."""
    if threads < 1:
        raise ValueError(f"library threads must be >= 1, got {threads}")
    return {**dict.fromkeys(LIBRARY_THREAD_VARS, str(threads)), THREADS_VAR: str(threads)}


def cap_library_threads() -> int | None:
    """Apply the cap of `THREADS_VAR` (when set) to what can be capped at run time: OpenCV
    (`cv2.setNumThreads`) and Open3D (`open3d.utility.set_max_threads`: TBB, which no environment
    variable bounds). OpenBLAS and OpenMP take theirs from the environment when they load, so the
    process must have started with `library_thread_env`. Returns the cap (None: none set)."""
    value = os.environ.get(THREADS_VAR)
    if not value:
        return None
    import cv2

    from workers.pipeline.geometry.open3d_light import load_open3d

    threads = int(value)
    cv2.setNumThreads(threads)
    load_open3d().utility.set_max_threads(threads)
    return threads


def pool_context(workers: int) -> multiprocessing.context.BaseContext:
    """`forkserver` where available (no fork of a process that may hold Open3D threads).

    Worker processes get thread pools of `cpu_count // workers` threads (set in the environment
    the server starts with, unless set already), so that `workers` processes do not
    oversubscribe the cores; `cap_library_threads` as a pool initializer caps Open3D too."""
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    for var, value in library_thread_env(threads).items():
        os.environ.setdefault(var, value)
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    # workers fork from a server that has already imported the job's modules and Open3D
    ctx.set_forkserver_preload(["workers.preload"])
    return ctx


#: the frames the fork server decodes before it forks workers (`start_pool_server`)
PRELOAD_FRAMES_VAR = "CITYTHERM_PRELOAD_FRAMES"
#: a frame source pickled larger than this is not handed to the fork server (environment limits)
_MAX_FRAMES_PICKLE = 96 * 1024


#: `(pid, frames)`: the fork server `start_pool_server` started last and the frames it decoded
#: (pickled, base64; None: none); a server of another pid was started otherwise, without frames
_SERVER_FRAMES: list[tuple[int | None, str | None]] = [(None, None)]


def _pickled_frames(frames: object | None) -> str | None:
    """`frames` pickled as the fork server's environment carries them (base64), None when there
    are none or they pickle larger than `_MAX_FRAMES_PICKLE`."""
    if frames is None:
        return None
    blob = base64.b64encode(pickle.dumps(frames)).decode("ascii")
    return blob if len(blob) <= _MAX_FRAMES_PICKLE else None


def start_pool_server(workers: int, frames: object | None = None) -> None:
    """Start the fork server of `pool_context(workers)` now (`workers > 1` and forkserver only),
    so that its imports (`workers.preload`, about 2 CPU s) overlap the job's first stages instead
    of delaying its first pool. The library-thread environment of `pool_context` is given to the
    server only: this process's own environment is left as it was (its libraries read theirs
    when they load).

    `frames`: the job's picklable frame source with a per-process cache of decoded frames
    (`db.sequence_package.PackageFrames`): the server decodes every frame once when they all
    fit in the cache (`workers.preload.decode_frames`), and every worker forked from it finds
    them decoded (copy on write) instead of decoding each frame again in each process.

    The fork server is one per process and decodes its frames once, when it starts: a server
    still running from an earlier job with other frames (or none) is stopped first and a new
    one started with this job's, so that each job's workers inherit its own frames and not the
    earlier job's (a server with the same frames is kept)."""
    if workers <= 1 or "forkserver" not in multiprocessing.get_all_start_methods():
        return
    blob = _pickled_frames(frames)
    pid = forkserver._forkserver._forkserver_pid
    if pid is not None and _SERVER_FRAMES[0] != (pid, blob):
        stop_pool_server()
    before = {var: os.environ.get(var) for var in (*LIBRARY_THREAD_VARS, THREADS_VAR, PRELOAD_FRAMES_VAR)}
    try:
        pool_context(workers)
        os.environ.pop(PRELOAD_FRAMES_VAR, None)
        if blob is not None:
            os.environ[PRELOAD_FRAMES_VAR] = blob
        forkserver.ensure_running()
        _SERVER_FRAMES[0] = (forkserver._forkserver._forkserver_pid, blob)
    finally:
        for var, value in before.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def stop_pool_server() -> None:
    """Stop this process's fork server, if one runs, once the workers forked from it have ended
    (a pool still open keeps it: this waits for it)."""
    server = forkserver._forkserver
    try:
        server._stop()  # CPython's own (tests use it); closes the server's "alive" pipe and waits
    except ChildProcessError:  # already ended and reaped
        server._forkserver_pid = server._forkserver_address = server._forkserver_alive_fd = None
    _SERVER_FRAMES[0] = (None, None)


#: `map(function, items)` for independent, picklable tasks, results in item order
TaskMap = Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]


def pool_map(workers: int) -> TaskMap:
    """A `map` for independent, picklable tasks (the orient stage's windows): in this process for
    `workers <= 1` or a single item, else in a process pool of up to `workers` processes in
    `pool_context(workers)`, made for the call and shut down when its results are consumed (or
    the iterator is closed). Results come in item order, each as soon as it and those before it
    are done; the first task that raises raises here."""

    def run(function: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        todo = list(items)
        if workers <= 1 or len(todo) <= 1:
            yield from map(function, todo)
            return
        ctx = pool_context(workers)
        n = min(workers, len(todo))
        with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=cap_library_threads) as pool:
            yield from pool.map(function, todo)

    return run
