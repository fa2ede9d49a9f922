"""Reading one large CityGML file with two reader processes: where to cut it, and the two halves
as well-formed documents.

In: a CityGML file path. Out: a `SplitPlan` (or None when the file is not cut) and, per half, the
`Spliced` bytes a reader parses instead of the file:

- first half: the file from its start up to the `cityObjectMember` start tag found at or after
  the cut (`split`; the middle of the file, or the fraction `at` of its size), then the end tag
  of the root element ("half" is used for either part whatever their sizes);
- second half: the file's header (from its start up to its first `cityObjectMember`: prolog,
  `CityModel` start tag with its namespace declarations, name, envelope, model-level
  appearances), as many newlines as the skipped part has (so that the lines of every error
  message are the file's), then the file from `split` to its end.

Each half is the document a reader of the whole file would see with the other half's members
left out, so it yields the same buildings, with the same ids and lines, in the same order. What
makes that true is checked: the cut lies at a `cityObjectMember` start tag (in XML a `<` in text
or in an attribute value is always escaped, so outside comments, CDATA sections and processing
instructions such a byte string is a start tag), and the file ends with the root's end tag
(`plan_split`); each reader checks its own part (`part_is_plain`: no comment, CDATA section,
processing instruction, DOCTYPE or appearance there, since a surface data registry or a
model-level appearance would tie the halves together). Ids the reader generates for top-level
buildings without `gml:id` count the buildings before them, so the second reader gives up
(`db.import_stream`) when it meets such a building, and the buildings of the second half are
then read from the whole file, the first half's skipped.
"""

from __future__ import annotations

import mmap
import re
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

__all__ = ["Spliced", "SplitPlan", "first_half", "part_is_plain", "plan_split", "scan_part", "second_half"]

_ROOT = re.compile(rb"<([A-Za-z_][\w.\-]*:)?CityModel[\s>]")
_MEMBER = re.compile(rb"<([A-Za-z_][\w.\-]*:)?cityObjectMember[\s>]")
#: bytes that must not occur in a half (after the header) for the halves to be independent: `!`
#: starts comments, CDATA sections and declarations, `?` processing instructions, `ppearance` is
#: in every appearance element (rare bytes, found with memchr; a `!` or `?` in a text only costs
#: the split)
_NOT_PLAIN = (b"!", b"?", b"ppearance")
#: the names of start tags of buildings and building parts with an attribute (`gml:id`), for
#: `scan_part` (one regular expression pass: about as fast as one `bytes.count`)
_BUILDING_TAG = re.compile(rb"Building(?:Part)? ")
_BUILDING_TAG_MAX = len(b"BuildingPart ")
_HEAD_BYTES = 1 << 20
_CHUNK = 1 << 22


@dataclass(frozen=True)
class SplitPlan:
    """Where a file is cut (byte offsets).

    Attributes:
        size: file size.
        header_end: start of the first `cityObjectMember` start tag (the header is before it).
        split: start of the `cityObjectMember` start tag at which the second half begins.
        root_qname: qualified name of the root element (e.g. `core:CityModel`).
    """

    size: int
    header_end: int
    split: int
    root_qname: str


def plan_split(path: Path, min_bytes: int, at: float = 0.5) -> SplitPlan | None:
    """Where to cut the file `path` in two (module docstring): at the first `cityObjectMember`
    from byte `at * size` on (`0 < at < 1`). None when the file is smaller than `min_bytes`, not
    in an ASCII-compatible encoding, its root is not a `CityModel` starting in its first MB, its
    header does not end there, or no `cityObjectMember` starts after that byte."""
    if not 0.0 < at < 1.0:
        raise ValueError(f"plan_split: the cut must lie inside the file (0 < at < 1), not {at}")
    size = path.stat().st_size
    if size < max(min_bytes, 1):
        return None
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        head = mm[:_HEAD_BYTES]
        if head[:2] in (b"\xfe\xff", b"\xff\xfe") or b"\x00" in head[:4]:
            return None  # UTF-16/32: the byte patterns below do not apply
        root = _ROOT.search(head)
        first = _MEMBER.search(head, root.end()) if root is not None else None
        if root is None or first is None or b"<!--" in head[: root.start()]:
            return None
        tag = first.group(0)[:-1]  # b"<core:cityObjectMember"
        pos = mm.find(tag, max(int(size * at), first.end()))
        while pos >= 0 and mm[pos + len(tag) : pos + len(tag) + 1] not in (b" ", b">", b"\t", b"\n", b"\r"):
            pos = mm.find(tag, pos + 1)
        root_qname = root.group(0)[1:-1]
        if pos < 0 or not mm[max(0, size - 4096) :].rstrip().endswith(b"</" + root_qname + b">"):
            return None
        qname = root_qname.decode("ascii")
        return SplitPlan(size=size, header_end=first.start(), split=pos, root_qname=qname)


def part_is_plain(path: Path, start: int, end: int) -> bool:
    """True when bytes `[start, end)` of `path` hold none of the markup that would make the halves
    depend on each other (comments, CDATA, processing instructions, DOCTYPE, appearances)."""
    return scan_part(path, start, end)[0]


def scan_part(path: Path, start: int, end: int) -> tuple[bool, int]:
    """(`part_is_plain`, an estimate of the buildings and building parts whose start tags lie in
    `[start, end)`: `Building ` and `BuildingPart ` as in `<bldg:Building gml:id=...`).
    The estimate is exact for the usual file (every building with a `gml:id`, none nested in a
    group); whoever uses it must check it against the buildings actually read."""
    overlap = max(*map(len, _NOT_PLAIN), _BUILDING_TAG_MAX) - 1
    count = 0
    with open(path, "rb") as f:
        f.seek(start)
        tail = b""
        while start < end:
            chunk = f.read(min(_CHUNK, end - start))
            if not chunk:
                break
            start += len(chunk)
            chunk = tail + chunk
            if any(needle in chunk for needle in _NOT_PLAIN):
                return False, count
            # a tag is counted in the chunk where it ends (`tail` repeats the previous one's end)
            seen = len(tail)
            found = _BUILDING_TAG.finditer(chunk, max(0, seen - _BUILDING_TAG_MAX))
            count += sum(1 for m in found if m.end() > seen)
            tail = chunk[-overlap:]
    return True, count


def _newlines(path: Path, start: int, end: int) -> int:
    """Number of newline bytes in `[start, end)` of `path`."""
    n = 0
    with open(path, "rb") as f:
        f.seek(start)
        while start < end:
            chunk = f.read(min(_CHUNK, end - start))
            if not chunk:
                break
            n += chunk.count(b"\n")
            start += len(chunk)
    return n


#: a piece of a spliced document: literal bytes, or a byte range `(start, end)` of the file
Piece = bytes | tuple[int, int]


def first_half(plan: SplitPlan) -> list[Piece]:
    """Pieces of the first half's document."""
    return [(0, plan.split), f"\n</{plan.root_qname}>\n".encode("ascii")]


def second_half(path: Path, plan: SplitPlan) -> list[Piece]:
    """Pieces of the second half's document (counts the newlines it skips: about 20 ms per 100 MB)."""
    pad = b"\n" * _newlines(path, plan.header_end, plan.split)
    return [(0, plan.header_end), pad, (plan.split, plan.size)]


class Spliced:
    """A read-only binary file of `pieces` (literal bytes and byte ranges of the file `path`), for
    a parser that reads it with `read(n)`."""

    def __init__(self, path: Path, pieces: list[Piece]) -> None:
        self._f = open(path, "rb")  # noqa: SIM115 - closed by close() / the context manager
        self._pieces = pieces
        self._i = 0
        self._off = 0

    def read(self, n: int = -1) -> bytes:
        """Up to `n` bytes (all that are left for n < 0; fewer at a piece boundary); b"" at the end."""
        while self._i < len(self._pieces):
            piece = self._pieces[self._i]
            if isinstance(piece, bytes):
                left = len(piece) - self._off
                start = self._off
            else:
                left = piece[1] - piece[0] - self._off
                start = piece[0] + self._off
            if left <= 0:
                self._i, self._off = self._i + 1, 0
                continue
            k = left if n < 0 else min(n, left)
            if isinstance(piece, bytes):
                out = piece[start : start + k]
            else:
                self._f.seek(start)
                out = self._f.read(k)
                if not out:
                    raise OSError(f"{self._f.name}: file shorter than when it was planned")
            self._off += len(out)
            return out
        return b""

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> Spliced:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
