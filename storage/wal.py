"""WAL checkpoints off the write path, for a long-lived process writing a SQLite file often.

SQLite's own auto-checkpoint runs inside the commit that crosses its threshold, and
with ``synchronous=NORMAL`` a checkpoint is two fsyncs: that commit -- and every writer
queued behind it -- waits milliseconds. ``Checkpointer`` runs ``PRAGMA
wal_checkpoint(PASSIVE)`` on a thread of its own instead (PASSIVE never blocks a writer
or a reader); the writers' connections set ``PRAGMA wal_autocheckpoint = 0``.

A PASSIVE checkpoint copies the WAL into the database but never starts the WAL over: the
next writer does, when it finds everything copied and no reader on the WAL, and
``journal_size_limit`` then cuts the file back. Under writes and reads that keep
overlapping (hundreds of transitions a second) that moment never comes and the WAL grows
without end, so a WAL past ``WAL_TRUNCATE_BYTES`` gets a TRUNCATE checkpoint: it holds new
writers back while it waits, at most ``TRUNCATE_WAIT_MS``, for the readers of old frames
to finish, then empties the file (busy: tried again at the next wake-up).
"""

from __future__ import annotations

import logging
import os
import sqlite3
import threading
from pathlib import Path

log = logging.getLogger(__name__)

#: A WAL larger than this is emptied by a TRUNCATE checkpoint (see the module's docstring).
WAL_TRUNCATE_BYTES = 32 << 20
#: The longest a TRUNCATE checkpoint waits for readers, holding new writers back meanwhile.
TRUNCATE_WAIT_MS = 100


class Checkpointer:
    """Checkpoints ``db_path`` every ``every`` commits noted by :meth:`committed`, at least every ``period_s``."""

    def __init__(self, db_path: Path, busy_timeout_ms: int, every: int = 200, period_s: float = 1.0) -> None:
        self._db_path, self._busy_timeout_ms, self._every, self._period_s = db_path, busy_timeout_ms, every, period_s
        self._commits = 0
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="wal-checkpoint", daemon=True)
        self._thread.start()

    def committed(self) -> None:
        """Note one commit (cheap; call it after each)."""
        self._commits += 1  # approximate under races: it only paces the wake-ups
        if self._commits >= self._every:
            self._commits = 0
            self._wake.set()

    def _run(self) -> None:
        try:
            conn = sqlite3.connect(self._db_path, isolation_level=None, check_same_thread=False)
            conn.execute(f"PRAGMA busy_timeout = {self._busy_timeout_ms}")
        except sqlite3.Error as exc:
            log.error("WAL checkpointer for %s cannot open the database: %s", self._db_path, exc)
            return
        failing = ""  # the error of the failing streak, said once (a full disk lasts, the wake-ups do not)
        try:
            while not self._stopping:
                self._wake.wait(self._period_s)
                self._wake.clear()
                try:
                    conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    if self._wal_bytes() > WAL_TRUNCATE_BYTES:
                        self._truncate(conn)
                except sqlite3.Error as exc:  # e.g. disk full: the next wake-up tries again
                    if str(exc) != failing:
                        log.warning("WAL checkpoint of %s failed: %s (retrying quietly)", self._db_path, exc)
                    failing = str(exc)
                    continue
                if failing:
                    log.warning("WAL checkpoint of %s works again", self._db_path)
                    failing = ""
        finally:
            conn.close()

    def _wal_bytes(self) -> int:
        try:
            return os.stat(f"{self._db_path}-wal").st_size
        except OSError:  # none (yet, or any more)
            return 0

    def _truncate(self, conn: sqlite3.Connection) -> None:
        """A TRUNCATE checkpoint that waits at most ``TRUNCATE_WAIT_MS`` for readers (busy: the next wake-up tries)."""
        conn.execute(f"PRAGMA busy_timeout = {TRUNCATE_WAIT_MS}")
        try:
            busy = conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0]
        finally:
            conn.execute(f"PRAGMA busy_timeout = {self._busy_timeout_ms}")
        if busy:
            log.debug("WAL of %s past %d bytes: readers held its truncation off; trying again", self._db_path,
                      WAL_TRUNCATE_BYTES)

    def stop(self) -> None:
        """Stop the thread (after the checkpoint in progress, if any)."""
        self._stopping = True
        self._wake.set()
        self._thread.join()
