"""The process pool context of the in-process job (`citytherm run --workers N`): the building units
(`workers.run.run_units`) and the split-half check (`workers.split_half`) share it."""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
import os

#: thread-pool sizes of numerical libraries (OpenBLAS, OpenMP, TBB users such as Open3D, OpenCV)
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TBB_NUM_THREADS")


def pool_context(workers: int) -> multiprocessing.context.BaseContext:
    """`forkserver` where available (no fork of a process that may hold Open3D threads).

    Worker processes get thread pools of `cpu_count // workers` threads (set in the environment
    the server starts with), so that `workers` processes do not oversubscribe the cores."""
    threads = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    for var in _THREAD_VARS:
        os.environ.setdefault(var, threads)
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    # workers fork from a server that has already imported the pipeline and Open3D (~1 s each)
    ctx.set_forkserver_preload(["workers.pipeline.units", "open3d"])
    return ctx
