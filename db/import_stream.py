"""Batches of buildings from a CityGML file for the importer, read in this process or in a
separate reader process so that parsing overlaps with writing to the database.

In: a CityGML path. Out: `("batch", transform([Building, ...]))` with up to `batch_size` top-level
buildings (parts nested), in document order (the transform runs where the file is read), and
`("appearance", Appearance)` for CityModel-level appearances that follow the buildings.

With `parallel=True` the file is parsed by a reader process started fresh (`subprocess`, a new
Python interpreter: it inherits no file descriptor but its three standard streams, so never a
database connection of this process) which sends the transformed batches as length-prefixed
pickles through a pipe (its standard output; at most one batch waits in the pipe, so memory stays
bounded). The reader dies with its parent: it asks the kernel for SIGKILL when the thread that
started it dies (Linux `PR_SET_PDEATHSIG`), checks that this parent is still the one that started
it, and stops at the first write into a pipe nobody reads any more. It ignores SIGINT, SIGTERM
and SIGHUP (a Ctrl-C reaches the whole process group, systemd signals the whole control group:
the importer decides, and stops the reader with SIGKILL). Use the stream as a
context manager (or call `close()`): leaving it stops the reader at once. Errors of the reader
are raised here (`CityGMLError` for a bad file); `peak_rss_mb` of the reader process is available
after the stream ends.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

from db.citygml import reader as citygml_reader
from db.citygml.names import CityGMLError
from workers.pipeline.geometry.citymodel import Building

__all__ = ["BatchStream"]

_LEN = struct.Struct("<Q")
#: the reader process's program: settings (a pickle) on standard input, frames on standard output.
_CHILD = (
    "import pickle, sys; cfg = pickle.load(sys.stdin.buffer); sys.path[:0] = cfg['sys_path']; "
    "from db.import_stream import _child_main; _child_main(cfg)"
)
_PR_SET_PDEATHSIG = 1


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


def _die_with_parent(parent_pid: int) -> None:
    """SIGKILL for this process when its parent dies (Linux); exit now if it is gone already."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)


def _send(out: BinaryIO, item: tuple[str, Any]) -> None:
    data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
    out.write(_LEN.pack(len(data)))
    out.write(data)
    out.flush()


def _child_main(cfg: dict[str, Any]) -> None:
    """Reader process: every batch, then ("done", peak RSS) or ("error", (kind, message, is_citygml))."""
    _die_with_parent(cfg["parent_pid"])
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    # frames go to a private copy of stdout; stray prints of libraries go to stderr instead
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    try:
        transform = pickle.loads(cfg["transform"])
        for item in _batches(Path(cfg["path"]), cfg["huge_tree"], cfg["batch_size"], transform):
            _send(out, item)
        _send(out, ("done", _peak_rss_mb()))
    except (BrokenPipeError, KeyboardInterrupt):  # the importer is gone or stopped us
        os._exit(1)
    except BaseException as exc:
        with contextlib.suppress(BrokenPipeError):
            _send(out, ("error", (type(exc).__name__, str(exc), isinstance(exc, CityGMLError))))
    os._exit(0)


def _read_exactly(f: BinaryIO, n: int) -> bytes | None:
    chunks = []
    while n > 0:
        b = f.read(n)
        if not b:
            return None
        chunks.append(b)
        n -= len(b)
    return b"".join(chunks)


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
    ) -> None:
        self.path = path
        self.batch_size = batch_size
        self.transform = transform
        self.huge_tree = huge_tree
        self.parallel = parallel and bool(sys.executable)  # an embedded interpreter cannot start one
        self.peak_rss_mb: float | None = None
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def reader_pid(self) -> int | None:
        """Process id of the reader process (None when reading in this process)."""
        return None if self._proc is None else self._proc.pid

    def start(self) -> BatchStream:
        """Start the reader process now (it then parses while the caller prepares the database)."""
        if self.parallel and self._proc is None:
            cfg = {
                "sys_path": [p for p in sys.path if p],
                "parent_pid": os.getpid(),
                "path": str(self.path),
                "huge_tree": self.huge_tree,
                "batch_size": self.batch_size,
                "transform": pickle.dumps(self.transform),
            }
            self._proc = subprocess.Popen(
                [sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, close_fds=True
            )
            assert self._proc.stdin is not None
            try:
                self._proc.stdin.write(pickle.dumps(cfg))
                self._proc.stdin.close()
            except BrokenPipeError:  # it died at once: reported by the first read
                pass
        return self

    def __enter__(self) -> BatchStream:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader process (if it still runs) and release its pipe."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.kill()  # it holds nothing worth a graceful end: a file it reads, a pipe
        try:
            proc.wait(timeout=10)
        finally:
            if proc.stdout is not None:
                proc.stdout.close()

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        if not self.parallel:
            yield from _batches(self.path, self.huge_tree, self.batch_size, self.transform)
            return
        self.start()
        proc = self._proc
        assert proc is not None and proc.stdout is not None
        try:
            while True:
                head = _read_exactly(proc.stdout, _LEN.size)
                body = None if head is None else _read_exactly(proc.stdout, _LEN.unpack(head)[0])
                if body is None:
                    code = proc.wait(timeout=10)
                    raise CityGMLError(f"reader process died (exit code {code})", path=self.path)
                kind, obj = pickle.loads(body)
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
            self.close()
