"""Writing leaf tiles, in this process or in a pool of processes.

In: a `LeafJob` per leaf: its buildings (model CRS), where to write the GLB, the tile's
`local_from_ecef` and what `content.tile_content` needs (the source with the figures of the
leaf's surfaces only, so that a job pickles small). Out: a `LeafDone` (the GLB's local bounds and
counts); the GLB file is written by whoever runs the job.

`LeafWriter(workers)` runs jobs as they come: with `workers <= 1` at once in this process, else
in a `ProcessPoolExecutor` (fork: the callers that ask for workers, the CLI and the bench, are
single-threaded; the API exports with one) with at most `2 · workers` jobs waiting, so memory
stays bounded however large the model. Results come back in submission order.
"""

from __future__ import annotations

import multiprocessing
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from db.tiles3d.content import tile_content
from db.tiles3d.frames import ecef_transform
from db.tiles3d.images import DisplayScale
from db.tiles3d.mesh import building_mesh
from db.tiles3d.source import ThermalSource
from workers.pipeline.geometry.citymodel import Building

__all__ = ["LeafDone", "LeafJob", "LeafWriter", "run_leaf"]


@dataclass(frozen=True, eq=False)
class LeafJob:
    """One leaf tile to write.

    Attributes:
        key: the caller's handle of the leaf (returned in `LeafDone`).
        path: GLB file to write.
        buildings: the leaf's top-level buildings (model CRS).
        source: the export's source (its `figures` cut down to the leaf's surfaces).
        geoid_undulation_m: as `TilesOptions`.
        local_from_ecef: `(4, 4)` the tile's local z-up frame from ECEF.
        display: the display colour scale.
    """

    key: int
    path: Path
    buildings: tuple[Building, ...]
    source: ThermalSource
    geoid_undulation_m: float | None
    local_from_ecef: np.ndarray
    display: DisplayScale


@dataclass(frozen=True, eq=False)
class LeafDone:
    """A written leaf: its key, local bounds `(3,)` each (z-up, metres) and counts."""

    key: int
    lo: np.ndarray
    hi: np.ndarray
    surfaces: int
    triangles: int
    images: int
    bytes: int


def run_leaf(job: LeafJob) -> LeafDone:
    """Triangulate the leaf's buildings, make and write its GLB."""
    src = job.source
    meshes = [building_mesh(b, src.theme) for b in job.buildings]
    ecef = ecef_transform(src.srs_name, job.geoid_undulation_m)
    res = tile_content(meshes, ecef, job.local_from_ecef, src.read_tile, src.values, job.display, src.figures)
    job.path.parent.mkdir(parents=True, exist_ok=True)
    job.path.write_bytes(res.glb)
    return LeafDone(job.key, res.lo, res.hi, res.surfaces, res.triangles, res.images, len(res.glb))


def leaf_source(source: ThermalSource, buildings: tuple[Building, ...]) -> ThermalSource:
    """`source` with only the figures of these buildings' polygons."""
    ids = {p.id for b in buildings for p in b.iter_polygons()}
    return replace(source, figures={k: v for k in ids if (v := source.figures.get(k)) is not None})


class LeafWriter:
    """Runs `LeafJob`s (see the module docstring); use as a context manager."""

    def __init__(self, workers: int = 1) -> None:
        self.workers = max(1, int(workers))
        self._pool: ProcessPoolExecutor | None = None
        self._waiting: deque[Future[LeafDone] | LeafDone] = deque()

    def __enter__(self) -> LeafWriter:
        if self.workers > 1:
            # forkserver: a fork of a process that runs threads (Open3D, a renderer's pool) can
            # deadlock in the child; the server forks from a clean process instead
            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
            self._pool = ProcessPoolExecutor(self.workers, mp_context=ctx)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def submit(self, job: LeafJob) -> Iterator[LeafDone]:
        """Queue a job; yields the results that are due (in order) to keep the queue short."""
        self._waiting.append(run_leaf(job) if self._pool is None else self._pool.submit(run_leaf, job))
        while len(self._waiting) > 2 * self.workers:
            yield self._result()

    def drain(self) -> Iterator[LeafDone]:
        """Yield every remaining result, in order."""
        while self._waiting:
            yield self._result()

    def _result(self) -> LeafDone:
        item = self._waiting.popleft()
        return item if isinstance(item, LeafDone) else item.result()
