"""Imports stopped from outside, on a real PostGIS: `citytherm import` of a large file (the NRW
tile replicated with new gml:ids, as the benchmarks build it) killed with SIGINT, SIGTERM and
SIGKILL while it writes batches and in its final step. Afterwards no model is left `importing`,
nothing of the stopped import is in the tables, the spatial indexes are in place and valid, the
reader process is gone, no connection is left (idle in transaction or otherwise), and an import
of the same name succeeds; a reader's spatial queries use the indexes and see no partial model
while an import runs. Models left `importing` by dead imports: `test_db_dead_imports.py`.

The kill points are chosen by watching the importer's progress lines (`--progress`: the rows it
writes are in its own uncommitted transaction, invisible to a count from another connection) and,
for the final step, by holding a row lock the final step of a replacement needs, so that the
importer is caught waiting in its final step (seen in `pg_stat_activity`).
"""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psycopg
import pytest
from typer.testing import CliRunner

from db.errors import ModelExistsError
from db.importer import ImportOptions, import_citygml
from db.ops import SPATIAL_INDEXES
from services.cli import app
from tests.conftest import DATA, REPO, replicated_nrw
from tests.integration.conftest import scalar

pytestmark = [pytest.mark.integration, pytest.mark.slow]

NRW = DATA / "nrw-tile-5659-citygml1-lod2.gml"
COPIES = 16  # ~38 MB: read by the reader process, 7 batches of 250 buildings
BUILDINGS, PARTS = 109 * COPIES, 55 * COPIES
PROGRESS = re.compile(r"progress: (\w+) (\d+) buildings (\d+) parts")
DEADLINE_S = 120.0  # generous bound for anything to happen on a busy machine


@pytest.fixture(scope="module")
def big_file(tmp_path_factory) -> Path:
    return replicated_nrw(tmp_path_factory.mktemp("faults") / "nrw-replicated.gml", COPIES)


@pytest.fixture(scope="module")
def keep_model(db_engine) -> dict:
    """A complete model that must survive everything here untouched: the NRW tile itself (the
    replicated file's first copy lies on it)."""
    s = import_citygml(db_engine, NRW, name="faults-keep", options=ImportOptions(parallel_read=False))
    return {"id": s.model_id, "buildings": s.buildings, "parts": s.parts, "surfaces": s.surfaces}


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    """A process that exists and is not a zombie (a zombie holds nothing; init may never reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_until(what: str, cond, timeout: float = 20.0) -> None:
    t = time.monotonic()
    while not cond():
        if time.monotonic() - t > timeout:
            raise AssertionError(f"not within {timeout:.0f} s: {what}")
        time.sleep(0.1)


class _CliImport:
    """`citytherm import FILE --name NAME --progress` in a subprocess; its stderr lines are read
    by a thread into a queue."""

    def __init__(self, url: str, path: Path, name: str, *extra: str) -> None:
        self.url = url
        self.server_start = scalar(url, "SELECT now()")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from services.cli import main; main()", "import", str(path),
             "--name", name, "--progress", "--database-url", url, *extra],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            # the importer handles SIGINT only when it is not ignored (a background shell ignores it)
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
            start_new_session=True,  # its own process group, to be signalled as a whole
        )  # fmt: skip
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stderr: list[str] = []
        self.stages: list[str] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line)
            self.lines.put(line)
        self.lines.put(None)

    def wait_progress(self, stage: str, min_buildings: int = 0) -> tuple[int, int]:
        """Block until a progress line of `stage` with at least `min_buildings`; (buildings, parts)."""
        t = time.monotonic()
        while time.monotonic() - t < DEADLINE_S:
            try:
                line = self.lines.get(timeout=1.0)
            except queue.Empty:
                continue
            if line is None:
                break
            m = PROGRESS.search(line)
            if m:
                self.stages.append(m.group(1))
                if m.group(1) == stage and int(m.group(2)) >= min_buildings:
                    return int(m.group(2)), int(m.group(3))
        self.proc.kill()
        raise AssertionError(f"no progress {stage!r} >= {min_buildings}: {''.join(self.stderr)[-2000:]}")

    def backends(self) -> list[tuple[int, str, str | None]]:
        """(pid, state, wait_event_type) of the connections the importer opened."""
        with psycopg.connect(self.url, autocommit=True) as c:
            return c.execute(
                "SELECT pid, state, wait_event_type FROM pg_stat_activity WHERE datname = current_database() "
                "AND backend_start >= %s AND pid <> pg_backend_pid() AND backend_type = 'client backend' "
                "AND (application_name LIKE 'citytherm import%%' OR application_name = '')",
                (self.server_start,),
            ).fetchall()

    def finish(self) -> tuple[int, str, str]:
        assert self.proc.stdout is not None
        out = self.proc.stdout.read()  # stderr is read by the thread
        self.proc.wait(timeout=DEADLINE_S)
        self.thread.join(timeout=DEADLINE_S)
        return self.proc.returncode, out, "".join(self.stderr)


def _kill(imp: _CliImport, sig: int, group: bool = False) -> tuple[int, str, list[int]]:
    """Send `sig` (to the importer's whole process group, as systemd does, when `group`), wait
    for the importer's end; (exit code, stderr, reader processes it had)."""
    readers = _children(imp.proc.pid)
    if group:
        os.killpg(imp.proc.pid, sig)
    else:
        imp.proc.send_signal(sig)
    code, _, err = imp.finish()
    return code, err, readers


def _assert_nothing_left(url: str, imp: _CliImport, readers: list[int], name: str, keep: dict) -> None:
    for pid in readers:
        _wait_until(f"reader process {pid} gone", lambda pid=pid: not _alive(pid))
    _wait_until("the importer's connections closed", lambda: imp.backends() == [])
    with psycopg.connect(url, autocommit=True) as c:
        assert c.execute("SELECT count(*) FROM city_model WHERE state <> 'complete'").fetchone()[0] == 0
        assert (
            c.execute("SELECT count(*) FROM city_model WHERE name LIKE %s", (f"{name}%",)).fetchone()[0] == 0
        )
        idle = c.execute(
            "SELECT count(*) FROM pg_stat_activity WHERE datname = current_database() "
            "AND state LIKE 'idle in transaction%%'"
        ).fetchone()[0]
        assert idle == 0
        valid = {
            r[0]
            for r in c.execute(
                "SELECT c.relname FROM pg_index i JOIN pg_class c ON c.oid = i.indexrelid "
                "WHERE i.indisvalid AND i.indisready"
            )
        }
        assert {n for n, _, _ in SPATIAL_INDEXES} <= valid
        # nothing of the stopped import in the tables: only complete models own rows
        orphans = c.execute(
            "SELECT (SELECT count(*) FROM building b WHERE NOT EXISTS "
            "        (SELECT 1 FROM city_model m WHERE m.id = b.city_model_id)) + "
            "       (SELECT count(*) FROM surface s WHERE NOT EXISTS "
            "        (SELECT 1 FROM city_model m WHERE m.id = s.city_model_id))"
        ).fetchone()[0]
        assert orphans == 0
        b, p, s = c.execute(
            "SELECT (SELECT count(*) FILTER (WHERE NOT is_part) FROM building WHERE city_model_id = %(m)s), "
            "(SELECT count(*) FILTER (WHERE is_part) FROM building WHERE city_model_id = %(m)s), "
            "(SELECT count(*) FROM surface WHERE city_model_id = %(m)s)",
            {"m": keep["id"]},
        ).fetchone()
        assert (b, p, s) == (keep["buildings"], keep["parts"], keep["surfaces"])


@pytest.mark.parametrize(
    ("sig", "share", "group"),
    [
        (signal.SIGINT, 0.0, False),
        (signal.SIGTERM, 0.35, False),
        (signal.SIGTERM, 0.5, True),
        (signal.SIGKILL, 0.65, False),
    ],
    ids=["sigint-first-batch", "sigterm-35pct", "sigterm-process-group-50pct", "sigkill-65pct"],
)
def test_kill_while_writing_batches(migrated_db, db_engine, big_file, keep_model, sig, share, group) -> None:
    name = f"faults-{signal.Signals(sig).name.lower()}{'-group' if group else ''}"
    imp = _CliImport(migrated_db, big_file, name)
    written, _ = imp.wait_progress("writing", max(1, int(share * BUILDINGS)))
    assert written < BUILDINGS  # caught while writing
    if share < 0.5:  # later, the reader may have sent its last batch and ended already
        assert _children(imp.proc.pid), "the big file is read by a reader process"
    # the import's rows are in its own transaction: nobody else sees them
    assert scalar(migrated_db, "SELECT count(*) FROM city_model WHERE name = %s", (name,)) == 0
    code, err, readers = _kill(imp, sig, group)
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        assert code == 128 + sig, err
        err = " ".join(err.split())
        assert f"interrupted by {signal.Signals(sig).name}: rolled back, nothing was written" in err
        assert "Traceback" not in err
    _assert_nothing_left(migrated_db, imp, readers, name, keep_model)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["sigterm", "sigkill"])
def test_kill_in_the_final_step_of_a_replacement(migrated_db, db_engine, big_file, keep_model, sig) -> None:
    """A replacement waits in its final step for a row lock (here: held by this test, as a job
    writing to the old model would): killed there, the old model stays as it was, and the server
    ends the importer's session at once, though it was waiting inside a statement."""
    name = f"faults-final-{signal.Signals(sig).name.lower()}"
    old = import_citygml(db_engine, NRW, name=name, options=ImportOptions(parallel_read=False))
    with psycopg.connect(migrated_db) as blocker:
        blocker.execute("SELECT 1 FROM city_model WHERE id = %s FOR SHARE", (old.model_id,))
        imp = _CliImport(migrated_db, big_file, name, "--replace")
        imp.wait_progress("finishing")
        _wait_until(
            "importer waiting for the row lock in its final step",
            lambda: [r[1:] for r in imp.backends() if r[1] == "active"] == [("active", "Lock")],
            timeout=DEADLINE_S,
        )
        code, err, readers = _kill(imp, sig)
        # the server has ended the session while this test still holds the lock it waited for
        _wait_until("the importer's connections closed", lambda: imp.backends() == [], timeout=10)
        blocker.rollback()
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL
    else:
        assert code == 128 + sig and "interrupted by SIGTERM" in " ".join(err.split()), err
    with psycopg.connect(migrated_db, autocommit=True) as c:
        rows = c.execute(
            "SELECT id, state, building_count, part_count FROM city_model WHERE name LIKE %s", (f"{name}%",)
        ).fetchall()
        assert rows == [(old.model_id, "complete", old.buildings, old.parts)]
        n = c.execute("SELECT count(*) FROM building WHERE city_model_id = %s", (old.model_id,)).fetchone()[0]
        assert n == old.buildings + old.parts
        c.execute("DELETE FROM city_model WHERE id = %s", (old.model_id,))  # cascades
    _assert_nothing_left(migrated_db, imp, readers, name, keep_model)


def _reader_queries(url: str, name: str, box: tuple[float, float, float, float], srid: int,
                    stop: threading.Event, samples: list[dict]) -> None:  # fmt: skip
    """Another user's spatial queries while an import runs: EXPLAIN (the GiST index must be usable:
    sequential scans off), and in one snapshot the surfaces in the keep model's box and whether the
    imported model exists; never waits on a lock."""
    env = "ST_MakeEnvelope(%s, %s, %s, %s, %s)"
    with psycopg.connect(url, autocommit=True) as c:
        c.execute("SET enable_seqscan = off")
        c.execute("SET lock_timeout = '3s'")
        c.execute("SET statement_timeout = '30s'")
        while not stop.is_set():
            sample: dict = {}
            for index, table, column in SPATIAL_INDEXES:
                plan = c.execute(
                    f"EXPLAIN (FORMAT JSON) SELECT id FROM {table} WHERE {column} && {env}", (*box, srid)
                ).fetchone()[0]
                sample[index] = f'"Index Name": "{index}"' in json.dumps(plan)
            c.execute("BEGIN ISOLATION LEVEL REPEATABLE READ")
            sample["surfaces"] = c.execute(
                f"SELECT count(*) FROM surface WHERE geometry && {env}", (*box, srid)
            ).fetchone()[0]
            sample["model"] = c.execute("SELECT state FROM city_model WHERE name = %s", (name,)).fetchall()
            c.execute("COMMIT")
            samples.append(sample)
            stop.wait(0.2)


def test_reader_keeps_its_index_during_an_import_and_the_name_imports_again(
    migrated_db, db_engine, big_file, keep_model
) -> None:
    """After the kills above, an import of the same name succeeds; meanwhile a reader's spatial
    queries use the GiST indexes, are never blocked, and see the model all or nothing (the
    replicated file's first copy lies exactly on the keep model's box: before the commit none of
    its surfaces is there, after it all); a second import of the name is refused at once while
    the first runs, and `db repair` lists it as running."""
    name = "faults-sigterm"  # killed above
    with psycopg.connect(migrated_db, autocommit=True) as c:
        srid, x0, y0, x1, y1 = c.execute(
            "SELECT srid, ST_XMin(envelope), ST_YMin(envelope), ST_XMax(envelope), ST_YMax(envelope) "
            "FROM city_model WHERE id = %s",
            (keep_model["id"],),
        ).fetchone()
        box = (x0, y0, x1, y1)
        in_box = c.execute(
            "SELECT count(*) FROM surface WHERE geometry && ST_MakeEnvelope(%s, %s, %s, %s, %s)", (*box, srid)
        ).fetchone()[0]
    assert in_box >= keep_model["surfaces"]
    stop, samples, errors = threading.Event(), [], []

    def run() -> None:
        try:
            _reader_queries(migrated_db, name, box, srid, stop, samples)
        except BaseException as exc:  # reported below
            errors.append(exc)

    reader = threading.Thread(target=run, daemon=True)
    imp = _CliImport(migrated_db, big_file, name)
    try:
        imp.wait_progress("writing")
        reader.start()
        with pytest.raises(ModelExistsError, match="being imported by another session"):
            import_citygml(db_engine, NRW, name=name, options=ImportOptions(parallel_read=False))
        res = CliRunner().invoke(app, ["db", "repair", "--dry-run", "--database-url", migrated_db])
        assert res.exit_code == 0 and f"import of {name} running" in " ".join(res.output.split()), res.output
        code, out, err = imp.finish()
    finally:
        stop.set()
        reader.join(timeout=60)
        if imp.proc.poll() is None:
            imp.proc.kill()
    assert errors == []
    assert code == 0, err
    assert f"{BUILDINGS} buildings, {PARTS} parts" in " ".join(out.split())
    assert "finishing" in " ".join(err.split())
    before = [s for s in samples if s["model"] == []]
    assert before, f"no reader query while the import wrote ({len(samples)} samples)"
    for s in samples:
        assert all(s[index] for index, _, _ in SPATIAL_INDEXES), s
        if s["model"] == []:
            assert s["surfaces"] == in_box, s  # nothing of the import before its commit
        else:
            assert s == {**s, "model": [("complete",)], "surfaces": in_box + keep_model["surfaces"]}
    with psycopg.connect(migrated_db, autocommit=True) as c:
        row = c.execute(
            "SELECT state, building_count, part_count FROM city_model WHERE name = %s", (name,)
        ).fetchone()
        assert row == ("complete", BUILDINGS, PARTS)
        c.execute("DELETE FROM city_model WHERE name = %s", (name,))  # cascades


def _fd_targets(pid: int) -> set[str]:
    """What the open file descriptors of process `pid` point to (`socket:[...]`, paths); a
    descriptor closed while it is listed is passed over."""
    out = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            out.add(os.readlink(f"/proc/{pid}/fd/{fd}"))
        except FileNotFoundError:
            continue
    return out


def test_reader_process_dies_with_its_parent(migrated_db, big_file) -> None:
    """The reader process started by a parent holding a database connection has no connection of
    it; when the parent is SIGKILLed (no clean-up runs), the reader dies too."""
    script = (
        "import os, sys, time\n"
        "import psycopg\n"
        "conn = psycopg.connect(sys.argv[2])\n"
        "from functools import partial\n"
        "from pathlib import Path\n"
        "from db.import_stream import BatchStream\n"
        "from db.import_rows import batch_lines\n"
        "s = BatchStream(Path(sys.argv[1]), batch_size=50, transform=partial(batch_lines, srid=25832, "
        "checks='fast'), parallel=True).start()\n"
        "print(s.reader_pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script, str(big_file), migrated_db],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert parent.stdout is not None
        reader = int(parent.stdout.readline())
        assert _alive(reader)
        own = _fd_targets(parent.pid)
        assert [f for f in own if f.startswith("socket:")]  # the parent's connection
        fds = _fd_targets(reader)
        assert not [f for f in fds if f.startswith("socket:")], fds  # no connection inherited
    finally:
        parent.kill()
        parent.wait()
    _wait_until("reader process gone", lambda: not _alive(reader))


def test_sigterm_in_process_rolls_back_and_restores_handlers(migrated_db, db_engine, monkeypatch) -> None:
    """A library caller's import (main thread) stopped by SIGTERM in its second batch:
    `ImportInterrupted`, nothing written, the default handlers back afterwards."""
    import db.importer as importer_mod

    real = importer_mod._write_lines
    calls = {"n": 0}

    def second_batch_signalled(conn, lines, model_id, ordinal0, **kw):
        calls["n"] += 1
        real(conn, lines, model_id, ordinal0, **kw)
        if calls["n"] == 2:
            signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(importer_mod, "_write_lines", second_batch_signalled)
    before = scalar(migrated_db, "SELECT count(*) FROM building")
    with pytest.raises(importer_mod.ImportInterrupted) as info:
        import_citygml(db_engine, NRW, name="faults-inproc", options=ImportOptions(batch_size=20))
    assert info.value.signum == signal.SIGTERM and calls["n"] == 2
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert scalar(migrated_db, "SELECT count(*) FROM city_model WHERE name = 'faults-inproc'") == 0
    assert scalar(migrated_db, "SELECT count(*) FROM building") == before


def test_a_signal_from_the_commit_on_waits_for_the_end() -> None:
    """After the commit a signal must not turn into `ImportInterrupted` (the model is complete):
    it is delivered again once the import's handlers are gone."""
    from db.import_signals import ImportInterrupted, Interrupts

    with pytest.raises(KeyboardInterrupt), Interrupts() as intr:
        intr.depth += 1  # as from the commit on
        signal.raise_signal(signal.SIGINT)
        assert intr.pending == signal.SIGINT and not intr.fired
    with pytest.raises(ImportInterrupted), Interrupts() as intr:
        signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
