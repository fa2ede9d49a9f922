"""Reading one CityGML file with two reader processes (`db.import_split`, `db.import_stream`): the
COPY rows are those of one reader, in the same order, whatever the file holds (comments,
appearances, buildings without `gml:id`, errors), and error lines are the file's."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import pytest
from lxml import etree

from db.citygml.names import CityGMLError
from db.import_rows import batch_lines
from db.import_split import Spliced, first_half, plan_split, second_half
from db.import_stream import BatchStream
from tests.conftest import REPO, replicated_nrw

COPIES = 4  # 436 buildings, 220 parts, ~9.5 MB


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return replicated_nrw(tmp_path_factory.mktemp("split") / "nrw-4.gml", COPIES)


def _rows(path: Path, split: int | None, batch_size: int = 50) -> tuple[list[str], list[str], str | None]:
    """Building and surface COPY rows (local links made relative, so batch boundaries do not
    matter) in the order the importer numbers them (the first part's "batch"es, then the second
    part's "batch2"es, which may come in between), and how the stream read the file. The first
    part's building count estimated from its bytes is checked against the buildings it gave."""
    transform = partial(batch_lines, srid=25832, checks="fast")
    buildings: dict[str, list[str]] = {"batch": [], "batch2": []}
    surfaces: dict[str, list[str]] = {"batch": [], "batch2": []}
    with BatchStream(path, batch_size=batch_size, transform=transform, split_above_bytes=split) as s:
        for kind, obj in s:
            assert kind == "batch" or (kind == "batch2" and split is not None)
            for i, (tail, parent, root) in enumerate(
                zip(obj.building_tails, obj.parent, obj.root, strict=True)
            ):
                buildings[kind].append(f"{tail}|{parent - i if parent >= 0 else 1}|{root - i}")
            surfaces[kind] += [
                f"{t}|{obj.building_tails[o].split(chr(9))[0]}"
                for t, o in zip(obj.surface_tails, obj.owner, strict=True)
            ]
        mode = s.mode
        if mode != "one":
            assert s.first_part_estimate == len(buildings["batch"])
            assert buildings["batch"] and (buildings["batch2"] or mode == "then whole")
        else:
            assert not buildings["batch2"]
    return buildings["batch"] + buildings["batch2"], surfaces["batch"] + surfaces["batch2"], mode


@pytest.fixture(scope="module")
def one_reader(model) -> tuple[list[str], list[str]]:
    b, s, mode = _rows(model, None)
    assert mode == "one" and len(b) == 109 * COPIES + 55 * COPIES
    return b, s


def _edit(src: Path, dst: Path, at: float, old: bytes, new: bytes) -> Path:
    """A copy of `src` with the first `old` after the fraction `at` of the file replaced by `new`."""
    data = src.read_bytes()
    k = data.index(old, int(len(data) * at))
    dst.write_bytes(data[:k] + new + data[k + len(old) :])
    return dst


def test_halves_are_the_file_cut_at_a_member(model) -> None:
    plan = plan_split(model, 1)
    assert plan is not None and plan.root_qname == "core:CityModel"
    data = model.read_bytes()
    assert data[plan.split :].startswith(b"<core:cityObjectMember>")
    assert len(data) // 2 <= plan.split < len(data) // 2 + 200_000
    assert data[plan.header_end :].startswith(b"<core:cityObjectMember>") and plan.header_end < 5000
    one = Spliced(model, first_half(plan))
    two = Spliced(model, second_half(model, plan))
    docs = [b"".join(iter(partial(f.read, 4096), b"")) for f in (one, two)]
    for f in (one, two):
        f.close()
    ids = [
        [b.get("{http://www.opengis.net/gml}id") for b in etree.fromstring(d).iter("{*}Building")]
        for d in docs
    ]
    whole = [b.get("{http://www.opengis.net/gml}id") for b in etree.fromstring(data).iter("{*}Building")]
    assert ids[0] + ids[1] == whole and len(ids[0]) > 0 and len(ids[1]) > 0
    # the second half keeps the file's line numbers
    last = list(etree.fromstring(docs[1]).iter("{*}Building"))[-1]
    assert last.sourceline == list(etree.fromstring(data).iter("{*}Building"))[-1].sourceline


def test_no_split_below_the_size_or_without_members(model, tmp_path) -> None:
    assert plan_split(model, model.stat().st_size + 1) is None
    members = tmp_path / "members.gml"
    members.write_bytes(model.read_bytes().replace(b"core:cityObjectMember", b"gml:featureMember"))
    assert plan_split(members, 1) is None


def test_two_readers_give_the_rows_of_one(model, one_reader) -> None:
    b, s, mode = _rows(model, 1)
    assert mode == "split"
    assert (b, s) == one_reader


@pytest.mark.parametrize(
    ("at", "old", "new", "mode"),
    [
        (0.25, b"<core:cityObjectMember>", b"<!-- a comment --><core:cityObjectMember>", "one"),
        (0.75, b"<core:cityObjectMember>", b"<!-- a comment --><core:cityObjectMember>", "then whole"),
        (0.75, b"<bldg:Building gml:id=", b"<bldg:Building gml:nid=", "then whole"),
    ],
    ids=["comment-first-half", "comment-second-half", "building-without-id-second-half"],
)
def test_a_half_that_depends_on_the_other_is_read_whole(model, tmp_path, at, old, new, mode) -> None:
    edited = _edit(model, tmp_path / "edited.gml", at, old, new)
    expected = _rows(edited, None)
    got = _rows(edited, 1)
    assert got[2] == mode
    assert got[:2] == expected[:2]
    if b"nid" in new:  # its generated id counts the buildings before it in the whole file
        assert [r for r in got[0] if r.startswith("building")] == [
            r for r in expected[0] if r.startswith("building")
        ]
        assert any(r.startswith("building") for r in got[0])


def test_an_error_in_the_second_half_names_the_file_line(model, tmp_path) -> None:
    edited = _edit(model, tmp_path / "broken.gml", 0.8, b"<gml:posList", b"<gml:posList <")
    with pytest.raises(CityGMLError) as one:
        _rows(edited, None)
    with pytest.raises(CityGMLError) as two:
        _rows(edited, 1)
    assert str(two.value) == str(one.value)
    line = edited.read_bytes()[: edited.read_bytes().index(b"<gml:posList <")].count(b"\n") + 1
    assert f"line {line}" in str(one.value) or f":{line}:" in str(one.value), str(one.value)


def test_both_readers_die_with_their_parent_and_inherit_no_socket(model) -> None:
    """The parent holds a socket (as an importer holds its connection) and is SIGKILLed (no
    clean-up runs): both reader processes go too, and neither ever had the socket."""
    script = (
        "import socket, sys, time\n"
        "from functools import partial\n"
        "from pathlib import Path\n"
        "from db.import_stream import BatchStream\n"
        "from db.import_rows import batch_lines\n"
        "a, b = socket.socketpair()\n"
        "s = BatchStream(Path(sys.argv[1]), batch_size=10, transform=partial(batch_lines, srid=25832, "
        "checks='fast'), split_above_bytes=1).start()\n"
        "print(*s.reader_pids, flush=True)\n"
        "time.sleep(600)\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script, str(model)], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    try:
        assert parent.stdout is not None
        readers = [int(p) for p in parent.stdout.readline().split()]
        assert len(readers) == 2
        assert any(_fd_targets(parent.pid, "socket:"))
        for pid in readers:
            assert not _fd_targets(pid, "socket:")
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in readers):
        assert time.monotonic() < deadline, "a reader outlived its parent"
        time.sleep(0.05)


def _fd_targets(pid: int, prefix: str) -> list[str]:
    out = []
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except FileNotFoundError:
            continue
        if target.startswith(prefix):
            out.append(target)
    return out


def _alive(pid: int) -> bool:
    """A process that exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_batches_parsed_ahead_until_the_transform_is_ready(model) -> None:
    """A reader whose transform has not come yet holds up to `AHEAD` full batches and parses on
    (`db.import_child.batches` with `ready`): the same batches in the same order."""
    from db.import_child import AHEAD, batches

    def ids(buildings: list) -> list[str]:
        return [b.id for b in buildings]

    calls = iter([False] * (AHEAD + 2) + [True] * 1000)  # not ready for longer than it may hold
    plain = list(batches(model, False, 20, ids))
    ahead = list(batches(model, False, 20, ids, ready=lambda: next(calls)))
    assert ahead == plain and len(plain) > AHEAD + 2
    late = iter([False] * 3 + [True] * 1000)
    assert list(batches(model, False, 20, ids, ready=lambda: next(late))) == plain

