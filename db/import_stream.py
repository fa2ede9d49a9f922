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
parsing one part (`db.import_split`: cut at a `cityObjectMember`, each part a well-formed document
with the file's header; the reader process's side is `db.import_child`). The first sends through
its pipe; the second writes into an unlinked temporary file. The first part's batches come as
("batch", ...) in order, the second part's as ("batch2", ...) in order, whenever the first reader
has none ready, so that the database never waits while either reader has a batch: the importer
numbers the second part's buildings from `first_part_estimate` (the first part's buildings and
parts counted from its bytes, sent by the first reader before its batches) and corrects them in
the rare file where that count was wrong. When a part is not independent of the other (comments,
appearances, ...: the first reader says so before it sends anything) the file is read by one
reader; when the second part has a top-level building without `gml:id` (its generated id counts
the buildings before it), or the second reader could not finish its temporary file, the
buildings after those it sent are read from the whole file. Both readers die with the importer
as the single one does. The readers can be started before the transform is known (`spawn`,
`prestart`): they load their modules and parse while the importer loads its own.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import logging
import os
import pickle
import select
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from functools import partial
from os import PathLike
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Any, BinaryIO

from db.import_child import LEN, batches
from db.import_options import ImportOptions
from db.import_split import SplitPlan, plan_split

if TYPE_CHECKING:  # this module imports nothing heavy: `prestart` runs before the database layer loads
    from workers.pipeline.geometry.citymodel import Building

__all__ = ["BatchStream", "prestart"]

log = logging.getLogger(__name__)

#: the reader process's program: settings (a pickle, base64) as its argument, the transform (a
#: pickle, read when the first batch is parsed) on standard input, which carries nothing else (so
#: that the reader can see whether it has come: `db.import_child.batches`); frames on standard
#: output.
_CHILD = (
    "import base64, pickle, sys; cfg = pickle.loads(base64.b64decode(sys.argv[1])); "
    "sys.path[:0] = cfg['sys_path']; from db.import_child import child_main; child_main(cfg)"
)


def _read_fd_exactly(fd: int, n: int) -> bytes | None:
    """`n` bytes from the file descriptor `fd` (a pipe), None at its end."""
    chunks = []
    while n > 0:
        b = os.read(fd, min(n, 1 << 20))
        if not b:
            return None
        chunks.append(b)
        n -= len(b)
    return b"".join(chunks)


def _pread_exactly(fd: int, n: int, pos: int) -> bytes:
    """`n` bytes of the file `fd` from offset `pos` (known to be there)."""
    chunks = []
    while n > 0:
        b = os.pread(fd, n, pos)
        if not b:
            raise OSError(f"temporary file of the second reader shorter than it was ({pos})")
        chunks.append(b)
        n -= len(b)
        pos += len(b)
    return b"".join(chunks)


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
        self._spill_pos = 0
        #: the first part's buildings and parts as estimated from its bytes (split files: the
        #: ordinals of the second part's "batch2" start there; the importer checks it)
        self.first_part_estimate: int | None = None
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
        arg = base64.b64encode(pickle.dumps(cfg)).decode("ascii")
        proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD, arg], stdin=subprocess.PIPE, stdout=stdout, close_fds=True
        )
        self._procs.append(proc)
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

    def _decode(self, body: bytes, first_part: bool = True) -> tuple[str, Any]:
        """A frame's (kind, object); a reader's end ("done") recorded, its error raised."""
        from db.citygml.names import CityGMLError

        kind, obj = pickle.loads(body)
        if kind == "done":
            rss = obj[0]
            self.peak_rss_mb = rss if self.peak_rss_mb is None else max(self.peak_rss_mb, rss)
            self.reader_cpu_s.insert(0 if first_part else len(self.reader_cpu_s), obj[2])
        elif kind == "error":
            name, message, is_citygml = obj
            if is_citygml:
                raise CityGMLError(message)
            raise RuntimeError(f"reading {self.path}: {name}: {message}")
        return kind, obj

    def _frame(self, read: Callable[[int], bytes | None], proc: subprocess.Popen[bytes]) -> tuple[str, Any]:
        """The next frame of a reader through `read` (`_read_exactly` of its pipe)."""
        from db.citygml.names import CityGMLError

        head = read(LEN.size)
        body = None if head is None else read(LEN.unpack(head)[0])
        if body is None:
            code = proc.wait(timeout=10)
            raise CityGMLError(f"reader process died (exit code {code})", path=self.path)
        return self._decode(body)

    def _frames(self, f: BinaryIO, proc: subprocess.Popen[bytes]) -> Iterator[tuple[str, Any]]:
        """The frames of one reader up to its end; returns ("done", (rss, count)) or ("unsplit", None)."""
        while True:
            kind, obj = self._frame(partial(_read_exactly, f), proc)
            if kind in ("done", "unsplit"):
                return kind, obj
            yield kind, obj

    def _spill_frame(self) -> tuple[str, Any] | None:
        """The next frame the second reader has written completely into its file, None if there
        is none yet (read with `pread`: the reader's file offset is left alone)."""
        assert self._spill is not None
        fd = self._spill.fileno()
        size = os.fstat(fd).st_size
        if size < self._spill_pos + LEN.size:
            return None
        (n,) = LEN.unpack(_pread_exactly(fd, LEN.size, self._spill_pos))
        if size < self._spill_pos + LEN.size + n:
            return None
        body = _pread_exactly(fd, n, self._spill_pos + LEN.size)
        self._spill_pos += LEN.size + n
        return self._decode(body, first_part=False)

    def _second_part(self, block: bool) -> tuple[str, Any] | None:
        """The second reader's next frame: ("batch", obj), ("done", ...), or ("failed", exit code)
        when it ended without finishing; None when it has none ready (`block`: wait for one)."""
        second = self._procs[1]
        while True:
            fr = self._spill_frame()
            if fr is not None:
                return fr
            code = second.poll()
            if code is not None:  # it ended: anything it wrote before is in the file now
                fr = self._spill_frame()
                return fr if fr is not None else ("failed", code)
            if not block:
                return None
            with contextlib.suppress(subprocess.TimeoutExpired):
                second.wait(timeout=0.01)

    def _split_batches(self) -> Iterator[tuple[str, Any]]:
        """The batches of a split file (module docstring): the first part's as ("batch", obj) in
        order, the second part's as ("batch2", obj) in order, written to the database whenever
        the first reader has nothing ready (the first part's building count, `first_part_estimate`,
        arrives first)."""
        first = self._procs[0]
        assert first.stdout is not None and self._spill is not None
        fd1 = first.stdout.fileno()  # read unbuffered, so that `poll` sees every byte not read yet
        read1 = partial(_read_fd_exactly, fd1)
        ready1 = select.poll()  # poll, not select: any descriptor number
        ready1.register(fd1, select.POLLIN)
        kind, obj = self._frame(read1, first)
        if kind == "unsplit":  # the first half is not independent: one reader for the whole file
            self.close()
            self.mode = "one"
            proc = self._spawn(subprocess.PIPE)
            assert proc.stdout is not None
            yield from self._frames(proc.stdout, proc)
            return
        if kind != "count":
            raise RuntimeError(f"reading {self.path}: first reader began with {kind!r}")
        self.first_part_estimate = obj
        pending: tuple[str, Any] | None = None  # a frame of the second reader not yet passed on
        second_state: str | None = None  # "done" or "failed" once the second reader has ended
        sent2 = 0  # batches of the second part passed on
        failed_code = 0
        while True:
            if pending is None and second_state is None:
                pending = self._second_part(block=False)
                if pending is not None and pending[0] in ("done", "failed"):
                    second_state, failed_code, pending = pending[0], pending[1], None
            # the first reader's frames first: it waits for us, the second one does not
            if ready1.poll(0 if pending is not None else 20):
                kind, obj = self._frame(read1, first)
                if kind == "done":
                    first_count = obj[1]
                    break
                yield kind, obj
            elif pending is not None:
                yield "batch2", pending[1]
                sent2 += 1
                pending = None
        if pending is not None:
            yield "batch2", pending[1]
            sent2 += 1
        while second_state is None:
            fr = self._second_part(block=True)
            assert fr is not None
            if fr[0] in ("done", "failed"):
                second_state, failed_code = fr[0], fr[1]
            else:
                yield "batch2", fr[1]
                sent2 += 1
        if second_state == "failed":
            # a building without gml:id in the second part (`NEEDS_WHOLE_FILE`), or the reader could
            # not finish its file: the rest from the whole file. Every batch it sent was full.
            self.mode = "then whole"
            proc = self._spawn(subprocess.PIPE, skip=first_count + sent2 * self.batch_size)
            assert proc.stdout is not None
            log.info("second reader ended with code %s: the rest read from the whole file", failed_code)
            for kind, obj in self._frames(proc.stdout, proc):
                yield ("batch2" if kind == "batch" else kind), obj

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        if not self.parallel:
            self.mode = "one"
            if self.transform is None:
                raise ValueError("BatchStream: no transform given")
            yield from batches(self.path, self.huge_tree, self.batch_size, self.transform)
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
