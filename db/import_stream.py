"""Batches of buildings from a CityGML file for the importer, read in this process or in a
separate reader process so that parsing overlaps with writing to the database.

In: a CityGML path. Out: `("batch", transform([Building, ...]))` with up to `batch_size` top-level
buildings (parts nested), in document order (the transform runs where the file is read), and
`("appearance", Appearance)` for CityModel-level appearances that follow the buildings. With
`parallel=True` a forked reader process parses the file (it never touches the database
connections it inherits and leaves with `os._exit`, as multiprocessing does) and sends the
transformed batches through a bounded queue (at most `queue_batches` in flight, so memory stays
bounded); its errors are raised here (`CityGMLError` for a bad file). `peak_rss_mb` of the reader
process is available after the stream ends.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from db.citygml import reader as citygml_reader
from db.citygml.names import CityGMLError
from workers.pipeline.geometry.citymodel import Building

__all__ = ["BatchStream"]


def _events(path: Path, huge_tree: bool) -> Iterator[tuple[str, Any]]:
    """("building", Building) in document order, and ("appearance", Appearance) for CityModel-level
    appearances after the buildings (when the reader's event stream reports them)."""
    stream = getattr(citygml_reader, "_Stream", None)
    if stream is None:  # pragma: no cover - reader without its event stream
        for b in citygml_reader.iter_buildings(path, huge_tree=huge_tree):
            yield "building", b
        return
    for kind, obj in stream(path, huge_tree).events():
        if kind in ("building", "appearance"):
            yield kind, obj


def _batches(
    path: Path, huge_tree: bool, batch_size: int, transform: Callable[[list[Building]], Any]
) -> Iterator[tuple[str, Any]]:
    pending: list[Building] = []
    for kind, obj in _events(path, huge_tree):
        if kind == "appearance":
            yield kind, obj
            continue
        pending.append(obj)
        if len(pending) >= batch_size:
            yield "batch", transform(pending)
            pending = []
    if pending:
        yield "batch", transform(pending)


def _peak_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # pragma: no cover - not Linux
        pass
    return float("nan")


def _produce(
    path: str, huge_tree: bool, batch_size: int, transform: Callable[[list[Building]], Any], q: Any
) -> None:
    """Reader process: put every batch, then ("done", peak RSS) or ("error", (kind, message))."""
    try:
        for item in _batches(Path(path), huge_tree, batch_size, transform):
            q.put(item)
        q.put(("done", _peak_rss_mb()))
    except BaseException as exc:
        q.put(("error", (type(exc).__name__, str(exc), isinstance(exc, CityGMLError))))


class BatchStream:
    """Iterate batches of buildings from `path` (see the module docstring)."""

    def __init__(
        self,
        path: Path,
        *,
        batch_size: int,
        transform: Callable[[list[Building]], Any] = list,
        huge_tree: bool = False,
        parallel: bool = True,
        queue_batches: int = 3,
    ) -> None:
        self.path = path
        self.batch_size = batch_size
        self.transform = transform
        self.huge_tree = huge_tree
        # a daemonic process (e.g. a Celery pool worker) may not have children: read in-process
        self.parallel = parallel and not mp.current_process().daemon and "fork" in mp.get_all_start_methods()
        self.queue_batches = queue_batches
        self.peak_rss_mb: float | None = None

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        if not self.parallel:
            yield from _batches(self.path, self.huge_tree, self.batch_size, self.transform)
            return
        ctx = mp.get_context("fork")
        q = ctx.Queue(maxsize=self.queue_batches)
        proc = ctx.Process(
            target=_produce,
            args=(str(self.path), self.huge_tree, self.batch_size, self.transform, q),
            daemon=True,
        )
        proc.start()
        try:
            while True:
                try:
                    kind, obj = q.get(timeout=5.0)
                except queue.Empty:
                    if not proc.is_alive():
                        raise CityGMLError(
                            f"reader process died (exit code {proc.exitcode})", path=self.path
                        ) from None
                    continue
                if kind == "done":
                    self.peak_rss_mb = obj
                    return
                if kind == "error":
                    name, message, is_citygml = obj
                    if is_citygml:
                        raise CityGMLError(message)
                    raise RuntimeError(f"reading {self.path}: {name}: {message}")
                yield kind, obj
        finally:
            if proc.is_alive():
                proc.terminate()
            proc.join(timeout=10)
            q.close()
