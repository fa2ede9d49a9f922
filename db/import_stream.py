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
are raised here (`CityGMLError` for a bad file); `peak_rss_mb` of the reader process (the largest
of them) is available after the stream ends.

With `split_above_bytes` a file at least that large is read by two reader processes at once, each
parsing one half (`db.import_split`: cut at a `cityObjectMember`, each half a well-formed document
with the file's header). The first sends through its pipe; the second writes into an unlinked
temporary file, read once the first half is done, so the batches keep the file's order. When a
half is not independent of the other (comments, appearances, ...: the first reader says so before
it sends anything) the file is read by one reader; when the second half has a top-level building
without `gml:id` (its generated id counts the buildings before it), or the second reader could not
finish its temporary file, the buildings after the first half are read from the whole file. Both
readers die with the importer as the single one does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import signal
import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from functools import partial
from os import PathLike
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Any, BinaryIO

from db.import_options import ImportOptions
from db.import_split import Spliced, SplitPlan, first_half, part_is_plain, plan_split, second_half

if TYPE_CHECKING:  # this module imports nothing heavy: `prestart` runs before the database layer loads
    from workers.pipeline.geometry.citymodel import Building

__all__ = ["BatchStream", "prestart"]

_LEN = struct.Struct("<Q")
#: the reader process's program: settings (a pickle) on standard input, then the transform (a
#: pickle, read when the first batch is parsed); frames on standard output.
_CHILD = (
    "import pickle, sys; cfg = pickle.load(sys.stdin.buffer); sys.path[:0] = cfg['sys_path']; "
    "from db.import_stream import _child_main; _child_main(cfg)"
)
_PR_SET_PDEATHSIG = 1
#: exit code of a second-half reader that met a top-level building without `gml:id`
_NEEDS_WHOLE_FILE = 3


class _GeneratedIdError(Exception):
    """A top-level building without `gml:id` in the second half of a split file."""


@dataclasses.dataclass
class _Part:
    """What one reader process reads: the whole file (`pieces` None) or a spliced half; `skip`
    top-level buildings left out first; `strict_ids`: stop at a building whose id is generated."""

    pieces: list[Any] | None = None
    skip: int = 0
    strict_ids: bool = False
    count: int = 0  # top-level buildings sent


def _events(path: Path, huge_tree: bool, part: _Part | None = None) -> Iterator[tuple[str, Any]]:
    """("building", Building) in document order, and ("appearance", Appearance) for CityModel-level
    appearances after the buildings."""
    from db.citygml import reader as citygml_reader

    part = part or _Part()
    source = None if part.pieces is None else partial(Spliced, path, part.pieces)
    seen = 0
    for kind, obj in citygml_reader._Stream(path, huge_tree, source=source).events():
        if kind == "building":
            seen += 1
            if seen <= part.skip:
                continue
            if part.strict_ids and obj.generated_id:
                raise _GeneratedIdError(obj.id)
            part.count += 1
            yield kind, obj
        elif kind == "appearance":
            yield kind, obj


def _batches(
    path: Path,
    huge_tree: bool,
    batch_size: int,
    transform: Callable[[list[Building]], Any],
    part: _Part | None = None,
) -> Iterator[tuple[str, Any]]:
    pending: list[Building] = []
    for kind, obj in _events(path, huge_tree, part):
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


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process so far, its start-up included."""
    t = os.times()
    return t.user + t.system


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


def _child_part(path: Path, cfg: dict[str, Any]) -> _Part | None:
    """The part this reader reads; None when its half of a split file is not independent."""
    half = cfg.get("half")
    if half is None:
        return _Part(skip=cfg.get("skip", 0))
    plan = SplitPlan(**cfg["plan"])
    start, end = (plan.header_end, plan.split) if half == 1 else (plan.split, plan.size)
    if not part_is_plain(path, start, end):
        return None
    pieces = first_half(plan) if half == 1 else second_half(path, plan)
    return _Part(pieces=pieces, strict_ids=half == 2)


class _LateTransform:
    """The importer's transform, read from standard input when the first batch is ready (the
    importer sends it once it knows the database SRID: parsing starts before)."""

    def __init__(self, src: BinaryIO) -> None:
        self._src = src
        self._fn: Callable[[list[Building]], Any] | None = None

    def __call__(self, buildings: list[Building]) -> Any:
        if self._fn is None:
            self._fn = pickle.load(self._src)
        return self._fn(buildings)


def _child_main(cfg: dict[str, Any]) -> None:
    """Reader process: every batch, then ("done", (peak RSS, top-level buildings sent, CPU s)) or
    ("error", (kind, message, is_citygml)); a split file's half that is not independent:
    ("unsplit", None) first (first half) or exit code `_NEEDS_WHOLE_FILE` (second half)."""
    _die_with_parent(cfg["parent_pid"])
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    # frames go to a private copy of stdout; stray prints of libraries go to stderr instead
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    path = Path(cfg["path"])
    from db.citygml.names import CityGMLError

    try:
        transform = _LateTransform(sys.stdin.buffer)
        part = _child_part(path, cfg)
        if part is None:
            if cfg["half"] == 2:
                os._exit(_NEEDS_WHOLE_FILE)
            _send(out, ("unsplit", None))
            os._exit(0)
        for item in _batches(path, cfg["huge_tree"], cfg["batch_size"], transform, part):
            _send(out, item)
        _send(out, ("done", (_peak_rss_mb(), part.count, _cpu_s())))
    except (BrokenPipeError, KeyboardInterrupt):  # the importer is gone or stopped us
        os._exit(1)
    except _GeneratedIdError:
        out.flush()
        os._exit(_NEEDS_WHOLE_FILE)
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
        transform: Callable[[list[Building]], Any] | None = list,
        huge_tree: bool = False,
        parallel: bool = True,
        split_above_bytes: int | None = None,
        split_at: float = 0.5,
    ) -> None:
        self.path = path
        self.batch_size = batch_size
        #: None until `start(transform)`: the readers parse their first batch meanwhile
        self.transform = transform
        self.huge_tree = huge_tree
        self.parallel = parallel and bool(sys.executable)  # an embedded interpreter cannot start one
        self.split_above_bytes = split_above_bytes
        self.split_at = split_at
        self.peak_rss_mb: float | None = None
        #: CPU seconds of each reader process that ended normally, start-up included
        self.reader_cpu_s: list[float] = []
        #: how the file was read: "one" reader, "split" in two, or split "then whole" file
        self.mode: str | None = None
        self._procs: list[subprocess.Popen[bytes]] = []
        self._spill: IO[bytes] | None = None
        self._plan: SplitPlan | None = None
        #: readers started before the transform was known: they wait for it on standard input
        self._waiting: list[subprocess.Popen[bytes]] = []

    @property
    def reader_pid(self) -> int | None:
        """Process id of the (first) reader process (None when reading in this process)."""
        return self._procs[0].pid if self._procs else None

    @property
    def reader_pids(self) -> list[int]:
        """Process ids of the reader processes running or not yet waited for."""
        return [p.pid for p in self._procs]

    def _spawn(self, stdout: int | IO[bytes], **part: Any) -> subprocess.Popen[bytes]:
        cfg = {
            "sys_path": [p for p in sys.path if p],
            "parent_pid": os.getpid(),
            "path": str(self.path),
            "huge_tree": self.huge_tree,
            "batch_size": self.batch_size,
            **part,
        }
        proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD], stdin=subprocess.PIPE, stdout=stdout, close_fds=True
        )
        self._procs.append(proc)
        assert proc.stdin is not None
        try:
            proc.stdin.write(pickle.dumps(cfg))
            proc.stdin.flush()
        except BrokenPipeError:  # it died at once: reported by the first read
            pass
        self._waiting.append(proc)
        self._send_transform()
        return proc

    def _send_transform(self) -> None:
        """Send the transform to the readers waiting for it (once it is known)."""
        if self.transform is None:
            return
        data = pickle.dumps(self.transform)
        waiting, self._waiting = self._waiting, []
        for proc in waiting:
            assert proc.stdin is not None
            with contextlib.suppress(BrokenPipeError):  # it died: reported by the first read
                proc.stdin.write(data)
                proc.stdin.close()

    def spawn(self) -> BatchStream:
        """Start the reader process(es) now, before the transform is known (`start` sends it):
        they load their modules and parse while the caller loads its own and prepares the
        database."""
        if not self.parallel or self._procs:
            return self
        if self.split_above_bytes is not None:
            self._plan = plan_split(self.path, self.split_above_bytes, at=self.split_at)
        if self._plan is None:
            self.mode = "one"
            self._spawn(subprocess.PIPE)
            return self
        self.mode = "split"
        plan = dataclasses.asdict(self._plan)
        self._spawn(subprocess.PIPE, half=1, plan=plan)
        self._spill = tempfile.TemporaryFile(prefix="citytherm-import-")  # noqa: SIM115 - closed by close()
        self._spawn(self._spill, half=2, plan=plan)
        return self

    def start(self, transform: Callable[[list[Building]], Any] | None = None) -> BatchStream:
        """Start the reader process(es) if `spawn` has not, with `transform` (when given: else
        the one of the constructor); they then parse while the caller prepares the database."""
        if transform is not None:
            self.transform = transform
        if self.transform is None:
            raise ValueError("BatchStream.start: no transform given")
        self.spawn()
        self._send_transform()
        return self

    def __enter__(self) -> BatchStream:
        return self.start() if self.transform is not None else self.spawn()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader processes (those still running) and release their pipes and files."""
        procs, self._procs = self._procs, []
        spill, self._spill = self._spill, None
        self._waiting = []
        try:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()  # it holds nothing worth a graceful end: a file it reads, a pipe
                if proc.stdin is not None and not proc.stdin.closed:
                    with contextlib.suppress(OSError):
                        proc.stdin.close()
            for proc in procs:
                try:
                    proc.wait(timeout=10)
                finally:
                    if proc.stdout is not None:
                        proc.stdout.close()
        finally:
            if spill is not None:
                spill.close()

    def _frames(self, f: BinaryIO, proc: subprocess.Popen[bytes]) -> Iterator[tuple[str, Any]]:
        """The frames of one reader up to its end; returns ("done", (rss, count)) or ("unsplit", None)."""
        from db.citygml.names import CityGMLError

        while True:
            head = _read_exactly(f, _LEN.size)
            body = None if head is None else _read_exactly(f, _LEN.unpack(head)[0])
            if body is None:
                code = proc.wait(timeout=10)
                raise CityGMLError(f"reader process died (exit code {code})", path=self.path)
            kind, obj = pickle.loads(body)
            if kind in ("done", "unsplit"):
                if kind == "done":
                    rss = obj[0]
                    self.peak_rss_mb = rss if self.peak_rss_mb is None else max(self.peak_rss_mb, rss)
                    self.reader_cpu_s.append(obj[2])
                return kind, obj
            if kind == "error":
                name, message, is_citygml = obj
                if is_citygml:
                    raise CityGMLError(message)
                raise RuntimeError(f"reading {self.path}: {name}: {message}")
            yield kind, obj

    def _split_batches(self) -> Iterator[tuple[str, Any]]:
        """The batches of a split file, in the file's order (module docstring)."""
        from db.citygml.names import CityGMLError

        first, second = self._procs
        assert first.stdout is not None and self._spill is not None
        kind, info = yield from self._frames(first.stdout, first)
        if kind == "unsplit":  # the first half is not independent: one reader for the whole file
            self.close()
            self.mode = "one"
            proc = self._spawn(subprocess.PIPE)
            assert proc.stdout is not None
            yield from self._frames(proc.stdout, proc)
            return
        code = second.wait()  # the first half is written: the second reader is done or nearly
        if code != 0:  # _NEEDS_WHOLE_FILE, or it could not finish its file (e.g. a full disk)
            self.mode = "then whole"
            proc = self._spawn(subprocess.PIPE, skip=info[1])
            assert proc.stdout is not None
            yield from self._frames(proc.stdout, proc)
            return
        self._spill.seek(0)
        kind, _ = yield from self._frames(self._spill, second)  # type: ignore[arg-type]
        if kind != "done":
            raise CityGMLError(f"second reader ended with {kind!r} (exit code {code})", path=self.path)

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        if not self.parallel:
            self.mode = "one"
            if self.transform is None:
                raise ValueError("BatchStream: no transform given")
            yield from _batches(self.path, self.huge_tree, self.batch_size, self.transform)
            return
        self.start()
        try:
            if self.mode == "split":
                yield from self._split_batches()
            else:
                proc = self._procs[0]
                assert proc.stdout is not None
                yield from self._frames(proc.stdout, proc)
        finally:
            self.close()


def prestart(path: str | PathLike[str], options: ImportOptions | None = None) -> BatchStream | None:
    """The reader processes of an import of `path` with `options`, started now, before the
    transform is known (None when the file is read in the importing process, or cannot be
    opened: the import reports that). A command line calls this before it loads the database
    layer, so that the readers load their modules and parse meanwhile; hand the stream to
    `db.importer.import_citygml(readers=...)`, which sends the transform, or close it."""
    opts = options or ImportOptions()
    p = Path(path)
    try:
        if not opts.reads_in_parallel(p):
            return None
    except OSError:
        return None
    return BatchStream(
        p,
        batch_size=opts.batch_size,
        transform=None,
        huge_tree=opts.huge_tree,
        parallel=True,
        split_above_bytes=opts.split_above_bytes,
        split_at=opts.split_at,
    ).spawn()
