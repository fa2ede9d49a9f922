"""The orient stage's windows as Celery tasks (`workers.service_windows`): which process runs a
window, with PostgreSQL's advisory locks and the broker replaced by in-memory stand-ins (the real
ones run in `tests/integration/test_workers.py`). Windows are stand-in tasks whose result is
computed from their index."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from workers import service_storage as storage
from workers import service_windows as sw


@dataclass(frozen=True)
class FakeWindow:
    index: int


@dataclass(frozen=True)
class FakeResult:
    index: int
    value: int


def square(task: FakeWindow) -> FakeResult:
    return FakeResult(task.index, task.index**2)


class Locks:
    """Advisory locks by name, held by this process (`job_lock`) or by another worker (`held`)."""

    def __init__(self) -> None:
        self.held: set[str] = set()
        self.mutex = threading.Lock()

    @contextmanager
    def job_lock(self, kind: str, job_id: uuid.UUID) -> Iterator[bool]:
        with self.mutex:
            got = kind not in self.held
            if got:
                self.held.add(kind)
        try:
            yield got
        finally:
            if got:
                with self.mutex:
                    self.held.discard(kind)


@pytest.fixture
def env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Locks, list[tuple], uuid.UUID]:
    locks, sent = Locks(), []
    monkeypatch.setattr(sw, "job_lock", locks.job_lock)
    monkeypatch.setattr(sw, "send", lambda name, *args, **kw: sent.append((name, *args)) or "id")
    monkeypatch.setattr(sw, "job_dir", lambda job_id: tmp_path / str(job_id))
    monkeypatch.setattr(sw, "job_status", lambda job_id: "running")
    return locks, sent, uuid.uuid4()


def counting(calls: list[int]):
    def run(task: FakeWindow) -> FakeResult:
        calls.append(task.index)
        return square(task)

    return run


def test_windows_are_queued_and_run_here_when_no_other_worker_takes_them(env) -> None:
    _, sent, jid = env
    calls: list[int] = []
    got = list(sw.celery_window_map(jid)(counting(calls), [FakeWindow(k) for k in range(3)]))
    assert got == [FakeResult(k, k * k) for k in range(3)]
    assert sent == [("citytherm.orient_window", str(jid), k) for k in range(3)]
    assert calls == [0, 1, 2]
    assert not sw.windows_dir(jid).exists()  # task and result files removed after the merge
    # a single window runs here, without tasks
    assert list(sw.celery_window_map(jid)(counting(calls), [FakeWindow(7)])) == [FakeResult(7, 49)]
    assert len(sent) == 3


def test_a_window_another_worker_holds_is_waited_for_and_not_run_twice(env) -> None:
    locks, _, jid = env
    locks.held.add("window-1")  # another worker runs window 1 ...

    def other_worker() -> None:  # ... and stores its result, then releases its lock
        time.sleep(0.3)
        storage.write_pickle(sw._result_path(jid, 1), FakeResult(1, -1))
        locks.held.discard("window-1")

    threading.Thread(target=other_worker).start()
    calls: list[int] = []
    got = list(sw.celery_window_map(jid, poll_s=0.02)(counting(calls), [FakeWindow(k) for k in range(3)]))
    assert calls == [0, 2]
    assert got == [FakeResult(0, 0), FakeResult(1, -1), FakeResult(2, 4)]


def test_a_result_another_worker_stored_is_taken_without_waiting_for_the_next_lock_try(
    env, monkeypatch: pytest.MonkeyPatch
) -> None:
    locks, _, jid = env
    locks.held.add("window-1")  # another worker runs window 1, stores it, keeps its lock a while
    stored = threading.Event()
    real_sleep = time.sleep

    def other_worker() -> None:
        real_sleep(0.2)
        storage.write_pickle(sw._result_path(jid, 1), FakeResult(1, -1))
        stored.set()

    naps: list[float] = []

    def nap(s: float) -> None:  # what the waiting side asks for (briefly slept here)
        naps.append(s)
        real_sleep(min(s, 0.01))

    monkeypatch.setattr(sw.time, "sleep", nap)
    threading.Thread(target=other_worker).start()
    calls: list[int] = []
    got = list(sw.celery_window_map(jid, poll_s=60.0)(counting(calls), [FakeWindow(0), FakeWindow(1)]))
    locks.held.clear()
    assert stored.is_set() and calls == [0]
    assert got == [FakeResult(0, 0), FakeResult(1, -1)]
    assert naps and max(naps) <= sw.LOOK_S  # looked for the file, never slept a lock try's interval


def test_a_window_whose_worker_died_is_run_here(env) -> None:
    locks, _, jid = env
    locks.held.add("window-0")

    def dies() -> None:  # SIGKILL: the connection, and with it the lock, is gone; no result
        time.sleep(0.2)
        locks.held.discard("window-0")

    threading.Thread(target=dies).start()
    calls: list[int] = []
    got = list(sw.celery_window_map(jid, poll_s=0.02)(counting(calls), [FakeWindow(0), FakeWindow(1)]))
    assert sorted(calls) == [0, 1] and got == [FakeResult(0, 0), FakeResult(1, 1)]


def test_a_repeated_prepare_reuses_the_stored_windows(env) -> None:
    _, sent, jid = env
    storage.write_pickle(sw._result_path(jid, 0), FakeResult(0, 100))
    calls: list[int] = []
    got = list(sw.celery_window_map(jid)(counting(calls), [FakeWindow(0), FakeWindow(1)]))
    assert calls == [1] and got == [FakeResult(0, 100), FakeResult(1, 1)]
    assert sent == [("citytherm.orient_window", str(jid), 1)]


def test_the_window_task(env, monkeypatch: pytest.MonkeyPatch) -> None:
    locks, _, jid = env
    monkeypatch.setattr(sw, "orient_window", square)
    assert sw.orient_window_task(str(jid), 0) == "gone"  # the prepare task merged the windows already
    storage.write_pickle(sw._task_path(jid, 0), FakeWindow(0))
    locks.held.add("window-0")
    assert sw.orient_window_task(str(jid), 0) == "busy"
    locks.held.clear()
    assert sw.orient_window_task(str(jid), 0) == "oriented"
    assert storage.read_pickle(sw._result_path(jid, 0)) == FakeResult(0, 0)
    assert sw.orient_window_task(str(jid), 0) == "done"
    storage.write_pickle(sw._task_path(jid, 1), FakeWindow(1))
    monkeypatch.setattr(sw, "job_status", lambda job_id: "dismissed")
    assert sw.orient_window_task(str(jid), 1) == "skipped"
    assert not sw._result_path(jid, 1).exists()


def test_a_window_that_raises_fails_the_stage_and_leaves_no_files(env) -> None:
    _, _, jid = env

    def fails_on_1(task: FakeWindow) -> FakeResult:
        if task.index == 1:
            raise ValueError("window 1 cannot be oriented")
        return square(task)

    with pytest.raises(ValueError, match="window 1"):
        list(sw.celery_window_map(jid)(fails_on_1, [FakeWindow(0), FakeWindow(1)]))
    assert not sw.windows_dir(jid).exists()


def test_idle_is_called_once_while_waiting_for_another_workers_window(env) -> None:
    locks, _, jid = env
    locks.held.add("window-1")
    idled: list[tuple[int, bool]] = []

    def other_worker() -> None:
        time.sleep(0.3)
        storage.write_pickle(sw._result_path(jid, 1), FakeResult(1, -1))
        locks.held.discard("window-1")

    threading.Thread(target=other_worker).start()
    calls: list[int] = []
    # when it is called, the windows this process could take are done, the held one is not
    idle = lambda: idled.append((len(calls), sw._result_path(jid, 1).exists()))  # noqa: E731
    run = sw.celery_window_map(jid, poll_s=0.02, idle=idle)
    got = list(run(counting(calls), [FakeWindow(k) for k in range(3)]))
    assert got == [FakeResult(0, 0), FakeResult(1, -1), FakeResult(2, 4)]
    assert idled == [(2, False)]


def test_idle_is_not_called_when_every_window_runs_here(env) -> None:
    _, _, jid = env
    idled: list[int] = []
    calls: list[int] = []
    run = sw.celery_window_map(jid, idle=lambda: idled.append(1))
    got = list(run(counting(calls), [FakeWindow(0), FakeWindow(1)]))
    assert got == [FakeResult(0, 0), FakeResult(1, 1)] and idled == []
