"""The durable request queue: collection requests in ``catalog.sqlite`` with leases and fencing.

Lifecycle (the only legal moves are in ``storage.requests.TRANSITIONS``)::

    queued --lease--> leased --complete--> done
    leased --fail / expire / worker_lost--> queued     (attempts + 1)
                                        \\-> dead       (when attempts reach max_attempts)
    leased --release--> queued                        (a graceful give-back: no attempt counted)
    queued | leased --cancel--> cancelled
    dead | cancelled --retry--> queued                (attempts reset to 0)

With ``lease(one_per_worker=True)`` (the service's) a worker that already holds a live lease is answered
with that one again (same token, a full term from now) rather than granted a second.

Attempts count the leases that ended *without* an episode, whatever ended them: a
``fail``, a lease that expired, or a worker whose liveliness was lost. So a request
that kills its worker every time still ends ``dead`` after ``max_attempts`` and never
loops. The fencing token is the lease number of the request (1 for its first lease,
2 for its second, ...): it only grows, even across ``retry``, so a worker holding an
older lease can never renew, complete or fail the request again.

Every transition is one ``BEGIN IMMEDIATE`` transaction on the queue's one writing connection,
which the threads of a process take in turn (a Python lock, not SQLite's busy handler, whose
sleeps were the p99 of a lease under load; one connection also keeps its page cache warm where
per-thread writers re-read every page the other threads had changed). Reads use per-thread connections.
SQLite specifics (the connection, pragmas, ``BEGIN IMMEDIATE``) stay inside
``RequestQueue``; its SQL (the table and the transitions' statements are ``storage.request_table``'s)
is otherwise plain, so a PostgreSQL backend can take its place behind the same methods (``lease``
becomes ``SELECT ... FOR UPDATE SKIP LOCKED``).
Durability: WAL with ``synchronous=NORMAL`` survives a crash of the process (SIGKILL).
What a caller is told is stored -- an enqueue, an operator's cancel / retry / prioritize --
is committed with ``synchronous=FULL`` (fsynced) and also survives a power loss; the
lease transitions are not (an fsync each would halve dispatch): a power loss can forget the
last leases and fails, which puts those requests back where they were -- the lease's worker
id still fences its upload. ``synchronous="FULL"`` fsyncs every change.

Speed: a lease-ending transition is one ``UPDATE ... WHERE <live lease> RETURNING`` inside its
transaction (the stale-token message is built from a second read only when it matched nothing),
and the indexes are partial, so a lease or a fail rewrites three pages, not nine. With
``background_checkpoint=True`` (the service) WAL checkpoints -- two fsyncs each -- run on a
thread of their own (``storage.wal``) instead of inside whichever transition crossed SQLite's threshold.
"""

from __future__ import annotations

import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from storage.database import configure, storage_error
from storage.errors import QueueClosedError, QueueError, StaleLeaseError
from storage.requests import (Lease, NewRequest, Request, RequestStatus, UnknownRequestError, check_transition,
                              finite_number)
from storage.request_table import (COLS, COMPLETE_SQL, COUNTS_SQL, DROPPED_INDEXES, END_ONE_SQL, FAIL_SQL, HELD_SQL,
                                   INSERT_SQL, LEASE_SQL, RELEASE_SQL, RENEW_SQL, SCHEMA, SCHEMA_OBJECTS, SELECT,
                                   TERMINAL_SQL, dumps, row_to_request)
from storage.wal import Checkpointer

_Q, _L, _D, _X, _C = (RequestStatus.QUEUED, RequestStatus.LEASED, RequestStatus.DONE,
                      RequestStatus.DEAD, RequestStatus.CANCELLED)


def steady_clock(wall: Callable[[], float] = time.time,
                 elapsed: Callable[[], float] = time.monotonic) -> Callable[[], float]:
    """Unix seconds that a step of the wall clock cannot move: ``wall`` when made, plus the time ``elapsed``
    since (``time.monotonic``, which NTP speeds or slows but never steps, and which stands still while the
    machine sleeps). The clock of a long-lived process that judges leases by its own time -- the service: with
    ``time.time``, an NTP step forward by more than a lease (or a VM or laptop resumed) expired every live
    lease at once, and each worker dropped the episode it was collecting; a step back kept a vanished worker's
    lease for the length of the step. Its timestamps (``created``, ``updated``) then differ from the wall
    clock by the steps since the process started; a restart reads the wall clock again, and carries the live
    leases over (``extend_leases``)."""
    start_wall, start = wall(), elapsed()
    return lambda: start_wall + (elapsed() - start)


class RequestQueue:
    """Collection requests in a SQLite file (usually the catalog's ``catalog.sqlite``), safe across threads."""

    def __init__(self, db_path: str | Path, *, clock: Callable[[], float] = time.time,
                 busy_timeout_s: float = 30.0, synchronous: str = "NORMAL",
                 background_checkpoint: bool = False, checkpoint_every: int = 200) -> None:
        """Open (creating if needed) the requests table in ``db_path``.

        clock: the time source used when a method gets no ``now``. background_checkpoint: run WAL
        checkpoints on a thread of this queue every ``checkpoint_every`` commits (and once a second)
        instead of inside a transition; for a long-lived process that writes a lot (the service).
        Raises QueueError on a bad file or setting.
        """
        if synchronous not in ("NORMAL", "FULL"):
            raise QueueError(f"synchronous: expected NORMAL or FULL, found {synchronous!r}")
        if checkpoint_every < 1:
            raise QueueError(f"checkpoint_every: expected >= 1, found {checkpoint_every}")
        self.db_path = Path(db_path)
        self._clock = clock
        self._busy_timeout_ms = int(busy_timeout_s * 1000)
        self._synchronous = synchronous
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        self._writer: sqlite3.Connection | None = None
        self._write_lock = threading.Lock()
        self._closed = False
        self._lease_sql: dict[tuple[int, int], str] = {}
        self._background_checkpoint = background_checkpoint
        self._checkpointer: Checkpointer | None = None
        if not self._schema_current():  # a read first: opening a current file takes no write lock
            with self._tx() as conn:
                for statement in SCHEMA:
                    conn.execute(statement)
        if background_checkpoint:
            self._checkpointer = Checkpointer(self.db_path, self._busy_timeout_ms, checkpoint_every)

    def _schema_current(self) -> bool:
        """Whether the file already has exactly ``SCHEMA``'s tables, indexes and triggers."""
        with self._reading() as conn:
            names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE tbl_name IN "
                                                "('requests', 'request_counts')")}
        return SCHEMA_OBJECTS <= names and not names & DROPPED_INDEXES

    # --- connections -----------------------------------------------------

    def _conn(self) -> sqlite3.Connection:
        """This thread's reading connection."""
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = self._open()
        return conn

    @contextmanager
    def _reading(self) -> Iterator[sqlite3.Connection]:
        """This thread's reading connection for a block; SQLite's errors become ``QueueError``."""
        try:
            yield self._conn()
        except sqlite3.Error as exc:
            raise storage_error(exc, QueueError, f"cannot read the queue on {self.db_path}: {exc}",
                                self.db_path) from exc

    def _open(self) -> sqlite3.Connection:
        if self._closed:
            raise QueueClosedError(f"the queue on {self.db_path} is closed")
        try:
            conn = sqlite3.connect(self.db_path, isolation_level=None, check_same_thread=False)
            configure(conn, self._busy_timeout_ms, self._synchronous)
            if self._background_checkpoint:
                conn.execute("PRAGMA wal_autocheckpoint = 0")  # the checkpointer thread does it
        except sqlite3.Error as exc:
            raise storage_error(exc, QueueError, f"cannot open the queue database {self.db_path}: {exc}",
                                self.db_path) from exc
        with self._lock:
            self._all.append(conn)
        return conn

    @contextmanager
    def _tx(self, conn: sqlite3.Connection | None = None, durable: bool = False) -> Iterator[sqlite3.Connection]:
        """One write transaction; with ``conn``, join the caller's open transaction instead.

        ``durable``: the commit is fsynced (``synchronous=FULL`` for this transaction) even when the
        queue runs with NORMAL -- for what a caller is told is stored (enqueue, operator actions).
        """
        if conn is not None:
            yield conn
            return
        with self._write_lock:
            if self._writer is None:
                self._writer = self._open()
            own = self._writer
            if durable and self._synchronous != "FULL":
                with self._synchronous_full(own):
                    yield from self._transaction(own)
            else:
                yield from self._transaction(own)
        if self._checkpointer is not None:
            self._checkpointer.committed()

    def _transaction(self, own: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
        """BEGIN IMMEDIATE, yield, COMMIT; ROLLBACK on any exception (SQLite's become QueueError)."""
        try:
            own.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as exc:
            raise storage_error(exc, QueueError, f"cannot start a transaction on {self.db_path}: {exc}",
                                self.db_path) from exc
        try:
            yield own
            own.execute("COMMIT")
        except sqlite3.Error as exc:
            self._rollback(own)
            raise storage_error(exc, QueueError, f"queue transaction on {self.db_path} failed: {exc}",
                                self.db_path) from exc
        except BaseException:
            self._rollback(own)
            raise

    @contextmanager
    def _synchronous_full(self, own: sqlite3.Connection) -> Iterator[None]:
        """``synchronous=FULL`` on the writer for one transaction, the queue's own level after it."""
        try:
            own.execute("PRAGMA synchronous = FULL")
        except sqlite3.Error as exc:
            raise storage_error(exc, QueueError, f"cannot make the commit durable on {self.db_path}: {exc}",
                                self.db_path) from exc
        try:
            yield
        finally:
            own.execute(f"PRAGMA synchronous = {self._synchronous}")

    @staticmethod
    def _rollback(conn: sqlite3.Connection) -> None:
        if conn.in_transaction:  # SQLite may already have rolled back (disk full, I/O error)
            conn.execute("ROLLBACK")

    def close(self) -> None:
        """Close every connection this queue opened (in any thread); call it once the threads are done."""
        with self._lock:
            self._closed = True
            conns, self._all = self._all, []
            checkpointer, self._checkpointer = self._checkpointer, None
            self._writer = None
        if checkpointer is not None:
            checkpointer.stop()
        for conn in conns:
            conn.close()
        self._local = threading.local()

    def __enter__(self) -> RequestQueue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _now(self, now: float | None) -> float:
        return self._clock() if now is None else float(now)

    # --- reading ---------------------------------------------------------

    def _fetch(self, conn: sqlite3.Connection, request_id: str) -> Request:
        row = conn.execute(f"{SELECT} WHERE id = ?", (request_id,)).fetchone()
        if row is None:
            raise UnknownRequestError(f"expected a known request id, found {request_id!r}")
        return row_to_request(row)

    def get(self, request_id: str) -> Request:
        """The request with this id; UnknownRequestError if none."""
        with self._reading() as conn:
            return self._fetch(conn, request_id)

    def resolve(self, id_or_prefix: str) -> str:
        """The id of the request whose id is ``id_or_prefix`` or uniquely starts with it (for operators);
        UnknownRequestError when none does or several do. Case-sensitive; a range on the primary key."""
        with self._reading() as conn:
            if not id_or_prefix:
                ids = []
            elif conn.execute("SELECT 1 FROM requests WHERE id = ?", (id_or_prefix,)).fetchone():
                return id_or_prefix
            else:
                after = id_or_prefix[:-1] + chr(ord(id_or_prefix[-1]) + 1)  # the first string past the prefix
                ids = [r[0] for r in conn.execute("SELECT id FROM requests WHERE id >= ? AND id < ? ORDER BY id "
                                                  "LIMIT 3", (id_or_prefix, after))]
        if len(ids) == 1:
            return ids[0]
        if ids:
            more = ", ..." if len(ids) > 2 else ""
            raise UnknownRequestError(f"request id prefix {id_or_prefix!r} is ambiguous ({', '.join(ids[:2])}{more})")
        raise UnknownRequestError(f"no request {id_or_prefix!r}: expected a known request id or a unique prefix")

    def list(self, status: RequestStatus | str | None = None, limit: int | None = None) -> list[Request]:
        """Requests, newest change first; with ``status`` queued, in the order they will be leased."""
        sql, args = SELECT, []
        if status is not None:
            try:
                status = RequestStatus(status)
            except ValueError:
                raise QueueError(f"status: expected one of {', '.join(s.value for s in RequestStatus)}, "
                                 f"found {status!r}") from None
            # Literals (enum values) so SQLite can pick the partial index; it needs the index's own
            # WHERE term spelled out in the query to know requests_finished holds the rows.
            sql += f" WHERE status = '{status.value}'"
            if status in (_D, _X, _C):
                sql += f" AND status IN {TERMINAL_SQL}"
        sql += (" ORDER BY priority DESC, rowid" if status == _Q
                else " ORDER BY updated DESC, rowid DESC")
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        with self._reading() as conn:
            return [row_to_request(r) for r in conn.execute(sql, args)]

    def counts(self) -> dict[str, int]:
        """Number of requests in every status (zeros included): the finished ones as the triggers keep them."""
        out = {s.value: 0 for s in RequestStatus}
        with self._reading() as conn:
            for status, n in conn.execute(COUNTS_SQL):
                out[status] = n
        return out

    # --- enqueue ---------------------------------------------------------

    def enqueue(self, new: NewRequest, *, now: float | None = None) -> tuple[Request, bool]:
        """Store a queued request; (request, created). An existing idempotency key returns (that one, False)."""
        return self.enqueue_many([new], now=now)[0]

    def enqueue_many(self, news: Sequence[NewRequest], *, now: float | None = None) -> list[tuple[Request, bool]]:
        """Several enqueues in one transaction (a planner's batch)."""
        t = self._now(now)
        out = []
        with self._tx(durable=True) as conn:
            for new in news:
                if new.idempotency_key is not None:
                    row = conn.execute(f"{SELECT} WHERE idempotency_key = ?", (new.idempotency_key,)).fetchone()
                    if row is not None:
                        out.append((row_to_request(row), False))
                        continue
                row = conn.execute(INSERT_SQL, (
                    uuid.uuid4().hex, t, t, new.priority, new.task, new.shape, dumps(new.start_state), new.policy,
                    dumps(new.policy_params), dumps(new.action_prefix), new.steps, dumps(new.reason),
                    new.max_attempts, new.idempotency_key)).fetchall()[0]
                out.append((row_to_request(row), True))
        return out

    # --- the lease -------------------------------------------------------

    def _lease_statement(self, n_tasks: int, n_shapes: int) -> str:
        key = (n_tasks, n_shapes)
        sql = self._lease_sql.get(key)
        if sql is None:
            filters = "".join(f" AND {column} IN ({', '.join('?' * n)})"
                              for column, n in (("task", n_tasks), ("shape", n_shapes)) if n)
            sql = self._lease_sql[key] = LEASE_SQL.format(filters=filters)
        return sql

    def lease(self, worker_id: str, tasks: Sequence[str] = (), shapes: Sequence[str] = (),
              lease_s: float = 30.0, now: float | None = None, *, one_per_worker: bool = False) -> Lease | None:
        """Lease the best queued request this worker can do, or None.

        Highest priority first, oldest first among equals; ``tasks`` / ``shapes`` empty means any.
        ``one_per_worker``: a worker that already holds a live lease gets that one back (``Lease.again``),
        with the same token and its expiry moved to at least now + lease_s, instead of a second one -- for
        workers that hold one lease at a time (the service's), whose lease query asked again after a reply
        came too late must not leave a lease behind that no worker knows of. Checked and granted in one
        transaction, so two such calls for one worker never both grant.
        """
        if not worker_id:
            raise QueueError("worker_id: expected a non-empty string, found ''")
        lease_s = finite_number("lease_s", lease_s, positive=True)
        sql = self._lease_statement(len(tasks), len(shapes))
        check_transition("lease", _Q, _L)
        check_transition("renew", _L, _L)  # what answering a held lease again does
        with self._tx() as conn:
            t = self._now(now)  # once the write lock is ours: a lease that waited for it gets its full term
            rows = conn.execute(HELD_SQL, (t + lease_s, t, worker_id)).fetchall() if one_per_worker else []
            again = bool(rows)
            if not again:
                rows = conn.execute(sql, (worker_id, t + lease_s, t, *tasks, *shapes)).fetchall()
        if not rows:
            return None
        request = row_to_request(rows[0])
        return Lease(request=request, token=request.token, expires_at=request.lease_expires, again=again)

    def _stale(self, conn: sqlite3.Connection, action: str, request_id: str, token: int,
               worker_id: str | None) -> StaleLeaseError:
        """The error for a lease-bound action whose ``WHERE <live lease>`` matched nothing (UnknownRequestError
        if the id is unknown)."""
        request = self._fetch(conn, request_id)
        return StaleLeaseError(
            f"{action} {request_id}: expected the live lease, found token {token} from "
            f"{worker_id or 'a worker'} while the request is {request.status.value} with token "
            f"{request.token} held by {request.worker_id}")

    def renew(self, request_id: str, token: int, worker_id: str | None = None, lease_s: float = 30.0,
              now: float | None = None) -> float:
        """Extend a live lease to now + lease_s; returns the new expiry. StaleLeaseError if not live."""
        lease_s = finite_number("lease_s", lease_s, positive=True)
        t = self._now(now)
        check_transition("renew", _L, _L)
        with self._tx() as conn:
            if not conn.execute(RENEW_SQL, (t + lease_s, t, request_id, token, worker_id, worker_id)).fetchall():
                raise self._stale(conn, "renew", request_id, token, worker_id)
        return t + lease_s

    def complete(self, request_id: str, token: int, episode_id: str, conn: sqlite3.Connection | None = None,
                 *, worker_id: str | None = None, now: float | None = None) -> bool:
        """Mark a leased request done with its episode; True if it changed, False if already done so.

        A repeat with the same token and episode (a duplicate upload) returns False and changes nothing;
        any other stale token / worker raises StaleLeaseError. ``conn``: run inside the caller's open
        transaction on the same database (Catalog.ingest_bytes(in_transaction=...)).
        """
        t = self._now(now)
        check_transition("complete", _L, _D)
        with self._tx(conn) as c:
            if c.execute(COMPLETE_SQL, (episode_id, t, request_id, token, worker_id, worker_id)).fetchall():
                return True
            request = self._fetch(c, request_id)
            if request.status == _D and request.token == token and request.episode_id == episode_id:
                return False
            raise self._stale(c, "complete", request_id, token, worker_id)

    def fail(self, request_id: str, token: int, error: str, *, worker_id: str | None = None,
             now: float | None = None) -> Request:
        """A worker gives its lease back with an error (counts an attempt). Returns the request after."""
        t = self._now(now)
        with self._tx() as conn:
            rows = conn.execute(FAIL_SQL, (str(error), t, request_id, token, worker_id, worker_id)).fetchall()
            if not rows:
                raise self._stale(conn, "fail", request_id, token, worker_id)
            request = row_to_request(rows[0])
            check_transition("fail", _L, request.status)  # raising here rolls the change back
        return request

    def release(self, request_id: str, token: int, *, worker_id: str | None = None,
                now: float | None = None) -> Request:
        """A draining worker gives its lease back unharmed: queued again, no attempt counted."""
        t = self._now(now)
        check_transition("release", _L, _Q)
        with self._tx() as conn:
            rows = conn.execute(RELEASE_SQL, (t, request_id, token, worker_id, worker_id)).fetchall()
            if not rows:
                raise self._stale(conn, "release", request_id, token, worker_id)
        return row_to_request(rows[0])

    def _end_leases(self, conn: sqlite3.Connection, leased: list[Request], action: str,
                    why: Callable[[Request], str], t: float) -> list[Request]:
        """Back to queued (or dead once attempts reach max_attempts), keeping the error; the requests after."""
        out = []
        for request in leased:
            rows = conn.execute(END_ONE_SQL, (why(request), t, request.id)).fetchall()
            after = row_to_request(rows[0])
            check_transition(action, request.status, after.status)
            out.append(after)
        return out

    def expire_leases(self, now: float | None = None) -> list[Request]:
        """End every lease past its expiry (an attempt each); the requests after the change."""
        t = self._now(now)
        with self._tx() as conn:
            rows = conn.execute(f"{SELECT} WHERE status = 'leased' AND lease_expires <= ?", (t,)).fetchall()
            return self._end_leases(conn, [row_to_request(r) for r in rows], "expire",
                                    lambda r: f"lease expired (worker {r.worker_id}, token {r.token})", t)

    def extend_leases(self, lease_s: float, now: float | None = None, *, exactly: bool = False) -> int:
        """Give every live lease at least ``lease_s`` more from now (never less than it had); the number
        extended. For after an outage of the storage, when no worker could renew. ``exactly``: every live lease
        ends ``lease_s`` from now, also one further out -- for a start-up, when the expiries were reckoned by the
        last process's clock (one a step of the wall clock put further out would hold a vanished worker's request
        for the length of the step)."""
        lease_s = finite_number("lease_s", lease_s, positive=True)
        t = self._now(now)
        with self._tx() as conn:
            return len(conn.execute("UPDATE requests SET lease_expires = ?, updated = ? WHERE status = 'leased' "
                                    f"{'' if exactly else 'AND lease_expires < ?'} RETURNING id",
                                    (t + lease_s, t) if exactly else (t + lease_s, t, t + lease_s)).fetchall())

    def reap_expired(self, now: float | None = None) -> int:
        """End every lease past its expiry; the number ended."""
        return len(self.expire_leases(now))

    def release_worker_leases(self, worker_id: str, now: float | None = None) -> list[Request]:
        """End every lease a lost worker holds (an attempt each); the requests after the change."""
        t = self._now(now)
        with self._tx() as conn:
            rows = conn.execute(f"{SELECT} WHERE status = 'leased' AND worker_id = ?", (worker_id,)).fetchall()
            return self._end_leases(conn, [row_to_request(r) for r in rows], "worker_lost",
                                    lambda r: f"worker {worker_id} lost (token {r.token})", t)

    def release_worker(self, worker_id: str, now: float | None = None) -> int:
        """End every lease a lost worker holds; the number ended."""
        return len(self.release_worker_leases(worker_id, now))

    # --- operator actions --------------------------------------------------

    def _operator(self, action: str, request_id: str, target: RequestStatus | None, sets: str,
                  args: tuple[Any, ...], now: float | None) -> Request:
        t = self._now(now)
        with self._tx(durable=True) as conn:
            request = self._fetch(conn, request_id)
            check_transition(action, request.status, target or request.status)
            rows = conn.execute(f"UPDATE requests SET {sets}, updated = ? WHERE id = ? RETURNING {COLS}",
                                (*args, t, request_id)).fetchall()
        return row_to_request(rows[0])

    def cancel(self, request_id: str, now: float | None = None) -> Request:
        """Cancel a queued or leased request (a leased one's worker then gets StaleLeaseError)."""
        return self._operator("cancel", request_id, _C, "status = 'cancelled', lease_expires = NULL", (), now)

    def retry(self, request_id: str, now: float | None = None) -> Request:
        """A dead or cancelled request back to queued with attempts reset (its last error is kept)."""
        return self._operator("retry", request_id, _Q, "status = 'queued', attempts = 0", (), now)

    def prioritize(self, request_id: str, priority: float, now: float | None = None) -> Request:
        """Set a request's priority (any status but done)."""
        return self._operator("prioritize", request_id, None, "priority = ?", (finite_number("priority", priority),),
                              now)
