"""The process pool's fork server (`workers.pool.start_pool_server`, `workers.preload`): it
decodes the job's frames once when they fit in the frame cache, so that the workers forked from
it find them decoded; this process's environment is left as it was."""

from __future__ import annotations

import base64
import os
import pickle
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from db.sequence_package import PackageFrames


def _frames(tmp_path, n: int) -> PackageFrames:
    import cv2

    import db.sequence_package as sp
    from workers.pipeline.geometry.manifest import Radiometry

    rng = np.random.default_rng(7)
    names = []
    for i in range(n):
        assert cv2.imwrite(str(tmp_path / f"{i}.png"), rng.integers(1, 60_000, (6, 8)).astype(np.uint16))
        names.append(f"{i}.png")
    return sp.PackageFrames(str(tmp_path), tuple(names), 8, 6, Radiometry(scale=0.01))


def test_the_server_decodes_every_frame_when_all_fit_in_the_cache(tmp_path, monkeypatch) -> None:
    import db.sequence_package as sp
    import workers.preload as pre

    frames = _frames(tmp_path, 5)
    blob = base64.b64encode(pickle.dumps(frames)).decode("ascii")
    monkeypatch.setattr(sp, "_FRAMES", type(sp._FRAMES)())
    monkeypatch.setattr(sp, "_CACHED_BYTES", [0])
    assert pre.decode_frames(blob) == 5
    assert len(sp._FRAMES) == 5 and sp._CACHED_BYTES[0] == 5 * 6 * 8 * 2
    calls = []
    monkeypatch.setattr(sp, "read_frame_raw", lambda p, n=None: calls.append(p))
    np.testing.assert_allclose(frames.load(3)[0, 0] * 100, float(frames.raw(3)[0, 0]), rtol=1e-5)
    assert calls == []  # decoded already: no file read
    # frames that would not all fit are not decoded (the cache would drop the first ones)
    monkeypatch.setattr(sp, "_FRAMES", type(sp._FRAMES)())
    monkeypatch.setattr(sp, "_CACHED_BYTES", [0])
    monkeypatch.setattr(pre, "FRAME_CACHE_BYTES", 4 * 6 * 8 * 2)
    zeros = np.zeros((6, 8), np.uint16)
    monkeypatch.setattr(sp, "read_frame_raw", lambda p, n=None: calls.append(p) or zeros.copy())
    assert pre.decode_frames(blob) == 0 and len(calls) == 1  # the first frame only, to size them
    assert pre.decode_frames("") == 0 and pre.decode_frames("not base64 pickle") == 0


def test_starting_the_server_leaves_this_process_environment_as_it_was(tmp_path, monkeypatch) -> None:
    import multiprocessing.forkserver as fs

    import workers.pool as pool

    seen = {}
    monkeypatch.setattr(fs, "ensure_running", lambda: seen.update(os.environ))
    for var in (*pool.LIBRARY_THREAD_VARS, pool.THREADS_VAR, pool.PRELOAD_FRAMES_VAR):
        monkeypatch.delenv(var, raising=False)
    before = dict(os.environ)
    pool.start_pool_server(2, _frames(tmp_path, 2))
    if "forkserver" in __import__("multiprocessing").get_all_start_methods():
        assert seen[pool.THREADS_VAR] == str(max(1, (os.cpu_count() or 1) // 2))
        assert pickle.loads(base64.b64decode(seen[pool.PRELOAD_FRAMES_VAR])).files == ("0.png", "1.png")
    assert dict(os.environ) == before
    seen.clear()
    pool.start_pool_server(1, _frames(tmp_path, 2))  # one worker: no pool, no server
    assert seen == {}


def _worker_state(_: int) -> tuple[list[str], int, int | None]:
    """In a pool worker: the files of the frames its process holds decoded (sorted), its nice
    value and the one the fork server's preload ran at."""
    import db.sequence_package as sp
    import workers.preload as pre

    return sorted(key[0] for key in sp._FRAMES), os.nice(0), pre.preloaded_at_nice[0]


def test_each_job_s_workers_inherit_that_job_s_frames(tmp_path, monkeypatch) -> None:
    import multiprocessing
    import multiprocessing.forkserver as fs
    from concurrent.futures import ProcessPoolExecutor

    import pytest

    import workers.pool as pool

    if "forkserver" not in multiprocessing.get_all_start_methods():
        pytest.skip("no forkserver on this platform")
    for var in (*pool.LIBRARY_THREAD_VARS, pool.THREADS_VAR):
        monkeypatch.setenv(var, "1")  # restored after: pool_context sets them in this process
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    jobs = {"a": _frames(tmp_path / "a", 3), "b": _frames(tmp_path / "b", 2)}
    seen, servers, nice = [], [], []
    try:
        for name in ("a", "b", "b", "a"):
            pool.start_pool_server(2, jobs[name])
            servers.append(fs._forkserver._forkserver_pid)
            with ProcessPoolExecutor(max_workers=1, mp_context=pool.pool_context(2)) as ex:
                paths, worker_nice, preload_nice = ex.submit(_worker_state, 0).result()
            seen.append(paths)
            nice.append((worker_nice, preload_nice))
    finally:
        pool.stop_pool_server()
    a = sorted(str(tmp_path / "a" / f"{i}.png") for i in range(3))
    b = sorted(str(tmp_path / "b" / f"{i}.png") for i in range(2))
    assert seen == [a, b, b, a]  # each job's workers hold its frames decoded, and only those
    # a job with other frames starts another server; one with the same frames keeps it
    assert servers[0] != servers[1] == servers[2] != servers[3]
    assert fs._forkserver._forkserver_pid is None
    # the server's imports and decoding ran below this process's priority, its workers at it
    import sys

    import workers.preload as pre

    mine = os.nice(0)
    lowered = min(mine + pre.PRELOAD_NICE, 19) if sys.platform == "linux" else None
    assert nice == [(mine, lowered)] * 4
