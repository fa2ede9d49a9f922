"""The reader process of an import (`db.import_stream`): it parses a CityGML file, or one part of
a split file, and sends the transformed batches as length-prefixed pickles on its standard output.

In: its settings (a pickle, base64, as its argument), the transform (a pickle on standard input,
read when the first batch is parsed: the importer sends it once it knows the database SRID; until
then the reader parses up to `AHEAD` batches ahead). Out: frames
`(kind, object)`: ("count", n) first for the first part of a split file (its buildings and parts
as estimated from its bytes, `db.import_split.scan_part`), ("batch", transform(buildings)) per
batch of top-level buildings, ("appearance", Appearance) for CityModel-level appearances after
the buildings, then ("done", (peak RSS MB, top-level buildings sent, CPU s)) or ("error", (kind,
message, is_citygml)); ("unsplit", None) when the first part of a split file is not independent
of the other (the second part's reader exits with `NEEDS_WHOLE_FILE` then, and when it meets a
top-level building without `gml:id`, whose generated id counts the buildings before it).

It dies with the importer (Linux `PR_SET_PDEATHSIG`, a parent check, a broken pipe) and ignores
SIGINT, SIGTERM and SIGHUP (the importer decides, and stops it with SIGKILL). Its modules (lxml,
numpy, the CityGML reader) are imported here, never by the importer's process before it needs them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import select
import signal
import struct
import sys
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from db.import_split import Spliced, SplitPlan, first_half, scan_part, second_half

if TYPE_CHECKING:
    from workers.pipeline.geometry.citymodel import Building

__all__ = ["LEN", "NEEDS_WHOLE_FILE", "batches", "child_main"]

LEN = struct.Struct("<Q")
_PR_SET_PDEATHSIG = 1
#: exit code of a second-half reader that met a top-level building without `gml:id`
NEEDS_WHOLE_FILE = 3


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
    #: first part of a split file: the buildings and parts its bytes seem to hold (`scan_part`)
    estimate: int | None = None


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


#: full batches a reader parses ahead while the importer has not sent the transform yet
AHEAD = 4


def batches(
    path: Path,
    huge_tree: bool,
    batch_size: int,
    transform: Callable[[list[Building]], Any],
    part: _Part | None = None,
    ready: Callable[[], bool] | None = None,
) -> Iterator[tuple[str, Any]]:
    """("batch", transform(buildings)) per `batch_size` top-level buildings and ("appearance",
    Appearance) as `_events` gives them, in document order. `ready` (optional) says whether
    `transform` can run without waiting (the importer has sent it): until then up to `AHEAD` full
    batches are held and parsing goes on, so that the reader does not sit idle while the importer
    starts."""
    pending: list[Building] = []
    held: list[list[Building]] = []

    def release() -> Iterator[tuple[str, Any]]:
        """The held batches, transformed, in order."""
        for h in held:
            yield "batch", transform(h)
        held.clear()

    for kind, obj in _events(path, huge_tree, part):
        if kind == "appearance":
            yield from release()
            yield kind, obj
            continue
        pending.append(obj)
        if len(pending) >= batch_size:
            if ready is not None and len(held) < AHEAD and not ready():
                held.append(pending)
            else:
                yield from release()
                yield "batch", transform(pending)
            pending = []
    yield from release()
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
    out.write(LEN.pack(len(data)))
    out.write(data)
    out.flush()


def _child_part(path: Path, cfg: dict[str, Any]) -> _Part | None:
    """The part this reader reads; None when its half of a split file is not independent."""
    half = cfg.get("half")
    if half is None:
        return _Part(skip=cfg.get("skip", 0))
    plan = SplitPlan(**cfg["plan"])
    start, end = (plan.header_end, plan.split) if half == 1 else (plan.split, plan.size)
    plain, estimate = scan_part(path, start, end)
    if not plain:
        return None
    if half == 1:
        return _Part(pieces=first_half(plan), estimate=estimate)
    return _Part(pieces=second_half(path, plan), strict_ids=True)


class _LateTransform:
    """The importer's transform, read from standard input when the first batch is ready (the
    importer sends it once it knows the database SRID: parsing starts before)."""

    def __init__(self, src: BinaryIO) -> None:
        self._src = src
        self._fn: Callable[[list[Building]], Any] | None = None

    def ready(self) -> bool:
        """True when the transform is here, or its bytes are waiting on standard input (a call
        would then not wait for the importer)."""
        if self._fn is not None:
            return True
        try:
            return bool(select.select([self._src.fileno()], [], [], 0)[0])
        except (OSError, ValueError):  # not a file descriptor select can watch: do not wait
            return True

    def __call__(self, buildings: list[Building]) -> Any:
        if self._fn is None:
            self._fn = pickle.load(self._src)
        return self._fn(buildings)


def child_main(cfg: dict[str, Any]) -> None:
    """Reader process: every batch, then ("done", (peak RSS, top-level buildings sent, CPU s)) or
    ("error", (kind, message, is_citygml)); the first half of a split file starts with ("count",
    buildings and parts estimated from its bytes); a half that is not independent: ("unsplit",
    None) first (first half) or exit code `NEEDS_WHOLE_FILE` (second half)."""
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
                os._exit(NEEDS_WHOLE_FILE)
            _send(out, ("unsplit", None))
            os._exit(0)
        if part.estimate is not None:
            _send(out, ("count", part.estimate))
        for item in batches(path, cfg["huge_tree"], cfg["batch_size"], transform, part, transform.ready):
            _send(out, item)
        _send(out, ("done", (_peak_rss_mb(), part.count, _cpu_s())))
    except (BrokenPipeError, KeyboardInterrupt):  # the importer is gone or stopped us
        os._exit(1)
    except _GeneratedIdError:
        out.flush()
        os._exit(NEEDS_WHOLE_FILE)
    except BaseException as exc:
        with contextlib.suppress(BrokenPipeError):
            _send(out, ("error", (type(exc).__name__, str(exc), isinstance(exc, CityGMLError))))
    os._exit(0)
