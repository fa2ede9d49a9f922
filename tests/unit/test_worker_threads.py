"""Library thread caps of the workers (issue 14): `citytherm worker` starts Celery in a fresh
interpreter whose environment caps OpenBLAS, OpenMP and OpenCV, and its pool processes cap OpenCV
and Open3D (`workers.pool.cap_library_threads`); the process pool of `citytherm run` gets the
same caps."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import typer
from typer.testing import CliRunner

from services.cli import app, worker_cmd
from workers.pool import LIBRARY_THREAD_VARS, THREADS_VAR, library_thread_env

PROBE = """
import json, os
import numpy as np
import cv2
import open3d as o3d
from workers.pool import cap_library_threads

cap = cap_library_threads()
a = np.random.default_rng(0).random((600, 600))
np.linalg.cholesky(a @ a.T + 600 * np.eye(600))  # BLAS
img = np.random.default_rng(1).random((1000, 1000)).astype(np.float32)
cv2.GaussianBlur(img, (15, 15), 3)  # OpenCV's pool
mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere(1.0, 50))
scene = o3d.t.geometry.RaycastingScene()
scene.add_triangles(mesh)
rays = np.tile(np.array([[0, 0, -5, 0, 0, 1]], np.float32), (200000, 1))
scene.cast_rays(o3d.core.Tensor(rays))  # TBB
print(json.dumps({"cap": cap, "cv2": cv2.getNumThreads(), "open3d": o3d.utility.get_max_threads(),
                  "os_threads": len(os.listdir("/proc/self/task"))}))
"""


def test_threads_default_to_the_cores_per_process() -> None:
    assert worker_cmd.library_threads(None, 1, cores=8) == 8
    assert worker_cmd.library_threads(None, 3, cores=8) == 2
    assert worker_cmd.library_threads(None, 4, cores=2) == 1
    assert worker_cmd.library_threads(0, 2, cores=8) == 0  # no cap
    assert worker_cmd.library_threads(3, 1, cores=8) == 3
    with pytest.raises(typer.BadParameter):
        worker_cmd.library_threads(-1, 1)
    env = library_thread_env(2)
    assert env[THREADS_VAR] == "2" and all(env[v] == "2" for v in LIBRARY_THREAD_VARS)
    with pytest.raises(ValueError):
        library_thread_env(0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts threads in /proc")
def test_a_capped_process_runs_its_libraries_on_one_thread() -> None:
    env = {k: v for k, v in os.environ.items() if k not in (*LIBRARY_THREAD_VARS, THREADS_VAR)}
    env.update(library_thread_env(1))
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got == {"cap": 1, "cv2": 1, "open3d": 1, "os_threads": 1}, got


class ExecError(Exception):
    """Raised by the stand-in of `os.execve`."""


def test_the_worker_command_restarts_itself_with_the_caps(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict = {}

    def execve(path: str, argv: list[str], env: dict[str, str]) -> None:
        seen.update(path=path, argv=argv, env=env)
        raise ExecError

    monkeypatch.setattr(worker_cmd.os, "execve", execve)
    monkeypatch.delenv(THREADS_VAR, raising=False)
    res = CliRunner().invoke(app, ["worker", "--concurrency", "2", "--threads", "1", "-n", "w@x"])
    assert isinstance(res.exception, ExecError), res.output
    assert seen["argv"][:5] == [sys.executable, "-m", "celery", "-A", "workers.celery_app"]
    assert seen["argv"][5:7] == ["worker", "--concurrency=2"] and "--hostname=w@x" in seen["argv"]
    assert all(seen["env"][v] == "1" for v in (*LIBRARY_THREAD_VARS, THREADS_VAR))


def test_the_worker_command_runs_in_place_when_capped_or_uncapped(monkeypatch: pytest.MonkeyPatch) -> None:
    import workers.celery_app as celery_app

    started: list[list[str]] = []

    class App:
        def worker_main(self, argv: list[str]) -> None:
            started.append(argv)

    monkeypatch.setattr(celery_app, "configure", lambda settings=None: App())
    monkeypatch.setattr(worker_cmd.os, "execve", lambda *a: pytest.fail("restarted"))
    assert CliRunner().invoke(app, ["worker", "--threads", "0"]).exit_code == 0  # no cap
    monkeypatch.setenv(THREADS_VAR, "1")
    assert CliRunner().invoke(app, ["worker", "--threads", "1"]).exit_code == 0  # the restarted one
    assert len(started) == 2 and all(a[0] == "worker" for a in started)
