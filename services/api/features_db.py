"""The database access of the OGC API - Features service (`features.py`, `features_sql.py`): the
queries of one request on one pooled connection, run by psycopg directly.

In: the app's SQLAlchemy `Engine` (its pool: checkout with pre-ping, sizes, invalidation) and SQL
text with `:name` bind parameters, as `sqlalchemy.text` takes it. Out: rows as tuples.

Why not `Connection.execute(text(...))`: a page is one or two small queries, and SQLAlchemy's
execution path (execution options, compiled-cache lookup, result metadata, isolation-level
reset) cost about 0.4 ms of CPU per request, as much as the rest of the service's Python
together (`docs/features.md`, Bench). The SQL is converted once per distinct text to psycopg's
`%(name)s` form by SQLAlchemy's own compiler (cached), so the bind syntax and escaping are
SQLAlchemy's; values are passed to psycopg as they are (as `text()` without types does).

Autocommit (the default) runs each query on its own, without BEGIN / ROLLBACK round trips, and
lets psycopg keep the statements it prepares (after `prepare_threshold` executions of the same
text: no planning per request); a transaction is only needed by a server-side cursor (`stream`).
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Iterator
from typing import Any

import psycopg
from psycopg.adapt import Loader
from sqlalchemy import Engine, text
from sqlalchemy.dialects.postgresql.psycopg import PGDialect_psycopg

__all__ = ["Db", "engine_key"]

_DIALECT = PGDialect_psycopg()
_KEYS: weakref.WeakKeyDictionary[Engine, str] = weakref.WeakKeyDictionary()


def engine_key(engine: Engine) -> str:
    """The database URL of `engine` as text, for per-process caches (made once per engine:
    rendering or hashing a SQLAlchemy URL costs some 20 µs)."""
    key = _KEYS.get(engine)
    if key is None:
        key = _KEYS[engine] = engine.url.render_as_string(hide_password=True)
    return key


@functools.lru_cache(maxsize=2048)
def psycopg_sql(sql: str) -> str:
    """`sql` with `:name` binds (SQLAlchemy `text()` syntax) in psycopg's form (`%(name)s`,
    literal `%` doubled), compiled by SQLAlchemy; cached per text.

    >>> psycopg_sql("SELECT x::text FROM t WHERE a = :a AND b LIKE '%y'")
    "SELECT x::text FROM t WHERE a = %(a)s AND b LIKE '%%y'"
    """
    return str(text(sql).compile(dialect=_DIALECT))


class _RawText(Loader):
    """Loads `text` values as the bytes PostgreSQL sent (UTF-8, the connection's encoding),
    undecoded: feature texts go to the response as they came."""

    def load(self, data: Any) -> bytes:
        """The value's bytes."""
        return bytes(data)


class Db:
    """One request's queries on one connection checked out of `engine`'s pool (pre-pinged).
    `autocommit` True: each statement on its own; False: in a transaction, rolled back on
    `close` (what a server-side cursor needs). `key` names the database for per-process caches.
    Close it (or use it as a context manager) to give the connection back."""

    def __init__(self, engine: Engine, *, autocommit: bool = True) -> None:
        self.key = engine_key(engine)
        self._fairy = engine.raw_connection()
        self._pg: psycopg.Connection = self._fairy.driver_connection  # type: ignore[assignment]
        self._autocommit = autocommit
        if autocommit:
            try:
                self._pg.autocommit = True
            except BaseException:
                self._fairy.close()
                raise

    def rows(
        self, sql: str, binds: dict[str, Any] | None = None, *, raw_text: bool = False
    ) -> list[tuple[Any, ...]]:
        """All rows of `sql` (`:name` binds from `binds`); `raw_text`: `text` values as `bytes`
        (UTF-8), not decoded."""
        with self._pg.cursor() as cur:
            if raw_text:
                cur.adapters.register_loader("text", _RawText)
            return self._run(cur, sql, binds).fetchall()

    def first(self, sql: str, binds: dict[str, Any] | None = None) -> tuple[Any, ...] | None:
        """The first row of `sql`, or None."""
        with self._pg.cursor() as cur:
            return self._run(cur, sql, binds).fetchone()

    def stream(
        self, sql: str, binds: dict[str, Any] | None = None, *, batch: int = 500, raw_text: bool = False
    ) -> Iterator[tuple]:
        """The rows of `sql` from a server-side cursor, fetched `batch` at a time (needs
        `autocommit=False`); `raw_text` as in `rows`."""
        assert not self._autocommit, "a server-side cursor needs a transaction"
        with self._pg.cursor(name="features_stream") as cur:
            if raw_text:
                cur.adapters.register_loader("text", _RawText)
            cur.itersize = batch
            self._run(cur, sql, binds)
            yield from cur

    def _run(self, cur: Any, sql: str, binds: dict[str, Any] | None) -> Any:
        try:
            return cur.execute(psycopg_sql(sql), binds or None)
        except psycopg.OperationalError:
            self._fairy.invalidate()  # the connection is gone: the pool makes a new one
            raise

    def close(self) -> None:
        """Give the connection back to the pool (rolled back when in a transaction; autocommit
        off again as the pool's other users expect)."""
        pg, fairy = self._pg, self._fairy
        try:
            if self._autocommit and not pg.closed:
                pg.autocommit = False
        finally:
            fairy.close()

    def __enter__(self) -> Db:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
