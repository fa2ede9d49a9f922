"""Signals during an import: SIGINT, SIGTERM and SIGHUP turned into `ImportInterrupted` in the
importing thread, and the import's transaction given up (`db.importer` uses them).

`Interrupts` (a context manager, main thread only) installs the handlers while the import runs;
`cancel_running` asks the server to cancel a running statement; `abandon` rolls the import's
connection back, or drops it when a statement may still be running (the server then rolls back
what a closed connection wrote).
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType, TracebackType
from typing import Any

import psycopg
from sqlalchemy import Connection

__all__ = ["STOP_SIGNALS", "ImportInterrupted", "Interrupts", "abandon", "cancel_running"]

log = logging.getLogger(__name__)


class ImportInterrupted(BaseException):
    """The import was stopped by a signal (SIGINT, SIGTERM, SIGHUP) and rolled back: nothing of it
    was written. A BaseException, like KeyboardInterrupt, so that `except Exception` handlers let
    it through; `signum` is the signal's number."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(
            f"import interrupted by {signal.Signals(signum).name}: rolled back, nothing was written"
        )


#: signals turned into `ImportInterrupted` during an import (when nobody else handles them).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Interrupts:
    """While active (main thread only), SIGINT/SIGTERM/SIGHUP raise `ImportInterrupted` once;
    inside `deferred()` (the clean-up) and from the commit on (`depth` raised for good) a signal
    is only noted. A signal noted before any interrupt is delivered again when the old handlers
    are back (after a commit: the model is complete, the process then stops as it was told); after
    an interrupt, further signals are dropped (the import is stopping already)."""

    def __init__(self) -> None:
        self.old: dict[int, Any] = {}
        self.fired = False
        self.pending: int | None = None
        self.depth = 0
        #: the import's connection: a statement running on it is cancelled by the interrupt
        self.conn: psycopg.Connection | None = None

    def __enter__(self) -> Interrupts:
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                current = signal.getsignal(sig)
                if current in (signal.SIG_DFL, signal.default_int_handler):
                    self.old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for sig, handler in self.old.items():
            signal.signal(sig, handler)
        if self.pending is not None and not self.fired:
            signal.raise_signal(self.pending)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.fired or self.depth:
            self.pending = self.pending or signum
            return
        self.fired = True
        cancel_running(self.conn)
        raise ImportInterrupted(signum)

    @contextmanager
    def deferred(self) -> Iterator[None]:
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1


def cancel_running(raw: psycopg.Connection | None) -> None:
    """Ask the server to cancel the statement running on `raw`, if one is (a closed connection
    alone is noticed only when the statement ends, or after `client_connection_check_interval`)."""
    if raw is None or raw.closed or raw.info.transaction_status != psycopg.pq.TransactionStatus.ACTIVE:
        return
    try:
        raw.cancel_safe(timeout=5.0)
    except Exception:  # best effort: closing the connection ends the session anyway
        log.debug("cancel request failed", exc_info=True)


def abandon(conn: Connection) -> None:
    """Roll the import's transaction back. When a statement may still be running (a signal came
    in the middle of it: SQLAlchemy then has dropped the connection already), cancel it and drop
    the connection: the server rolls back what a closed connection wrote."""
    if conn.invalidated:
        return
    try:
        raw = conn.connection.driver_connection
        if raw is not None and raw.info.transaction_status == psycopg.pq.TransactionStatus.ACTIVE:
            cancel_running(raw)
            conn.invalidate()
            return
        conn.rollback()
    except Exception:  # the connection is unusable: closing it rolls back on the server
        log.debug("rollback failed; dropping the connection", exc_info=True)
        conn.invalidate()
