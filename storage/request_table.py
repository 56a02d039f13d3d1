"""The ``requests`` table: its schema, the statements of the queue's transitions, and its rows.

``SCHEMA`` brings any file to the current table, indexes and counts (it drops the full indexes of the first
version and makes the partial ones, and counts a file from before ``request_counts``); ``SCHEMA_OBJECTS`` and
``DROPPED_INDEXES``, read off it, tell a current file from one that needs it. Each lease-bound statement
(``RENEW_SQL``, ``COMPLETE_SQL``, ``RELEASE_SQL``, ``FAIL_SQL``) matches only the live lease -- the id,
``leased``, the fencing token and, when given, the worker -- and most return the row after the change
(``COLS``), which ``row_to_request`` makes a ``storage.requests.Request``; ``HELD_SQL`` answers a worker's live
lease again. ``dumps`` writes a request's JSON fields.

This is SQL text and row conversion only: ``storage.queue.RequestQueue`` owns the connections, the
transactions and the checks of ``storage.requests.TRANSITIONS``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from typing import Any

from storage.database import kept_counts
from storage.errors import QueueError
from storage.requests import Request, RequestStatus

_COLUMNS = ("id", "created", "updated", "priority", "task", "shape", "start_state", "policy",
            "policy_params", "action_prefix", "steps", "reason", "attempts", "max_attempts", "status",
            "worker_id", "token", "lease_expires", "last_error", "idempotency_key", "episode_id")
COLS = ", ".join(_COLUMNS)
SELECT = f"SELECT {COLS} FROM requests"
TERMINAL_SQL = "('done', 'dead', 'cancelled')"

SCHEMA = (
    """CREATE TABLE IF NOT EXISTS requests (
        id TEXT PRIMARY KEY,
        created REAL NOT NULL,
        updated REAL NOT NULL,
        priority REAL NOT NULL,
        task TEXT NOT NULL,
        shape TEXT NOT NULL,
        start_state TEXT NOT NULL,
        policy TEXT NOT NULL,
        policy_params TEXT NOT NULL,
        action_prefix TEXT NOT NULL,
        steps INTEGER NOT NULL,
        reason TEXT NOT NULL,
        attempts INTEGER NOT NULL DEFAULT 0,
        max_attempts INTEGER NOT NULL,
        status TEXT NOT NULL,
        worker_id TEXT,
        token INTEGER NOT NULL DEFAULT 0,
        lease_expires REAL,
        last_error TEXT,
        idempotency_key TEXT UNIQUE,
        episode_id TEXT
    )""",
    # Full indexes of the first version: every one of them was rewritten by every transition.
    "DROP INDEX IF EXISTS requests_ready",
    "DROP INDEX IF EXISTS requests_expiry",
    "DROP INDEX IF EXISTS requests_worker",
    "DROP INDEX IF EXISTS requests_status",
    # Leasing was by (priority, created) before, on the index requests_queued: ``created`` is the service's clock,
    # so after a restart that found the wall clock stepped back, newer requests sorted ahead of older ones of the
    # same priority. That index is left where it is (not dropped): an older service running on the file as it is
    # upgraded leases through it, and without it sorted every queued row per lease (50 ms at 100k queued).
    # Partial indexes: a row is in the one index of its status, so a transition rewrites the table
    # page and at most two index pages. Queries name the status as a literal so SQLite can use them.
    # Leasing walks this one in (priority, arrival) order and stops at the first capable row: the rowid, which
    # every index entry ends with, counts up with each insert, whatever any clock says (FIFO among equals).
    "CREATE INDEX IF NOT EXISTS requests_fifo ON requests (priority DESC) WHERE status = 'queued'",
    # Expiry and a lost worker's leases (a handful of rows: one per busy worker).
    "CREATE INDEX IF NOT EXISTS requests_leased ON requests (lease_expires) WHERE status = 'leased'",
    "CREATE INDEX IF NOT EXISTS requests_finished ON requests (status, updated) WHERE status IN "
    + TERMINAL_SQL,
    # The number of finished requests in each status, kept by triggers in every write's own transaction (any
    # process's, any code version's), so ``counts`` -- the service's once-a-second gauge -- reads a handful of
    # rows, not a history that never shrinks (see BENCHMARKS, "Counting a long history"); queued and leased
    # requests, the live ones, are counted from their partial indexes, so a lease, a renewal or a fail fires no
    # trigger. A file from before it is counted once, in the transaction that makes the triggers.
    *kept_counts("requests", "status", "request_counts", TERMINAL_SQL),
)
# What a current file has and must not have, read off SCHEMA (so the two cannot drift apart).
SCHEMA_OBJECTS = {m[1] for sql in SCHEMA if (m := re.match(r"CREATE \w+ IF NOT EXISTS (\w+)", sql))}
DROPPED_INDEXES = {m[1] for sql in SCHEMA if (m := re.match(r"DROP INDEX IF EXISTS (\w+)", sql))}

# Each transition is one statement (prepared once per connection by sqlite3's statement cache).
_LIVE = "id = ? AND status = 'leased' AND token = ? AND (? IS NULL OR worker_id = ?)"
LEASE_SQL = ("UPDATE requests SET status = 'leased', worker_id = ?, token = token + 1, lease_expires = ?,"
             " updated = ? WHERE id = (SELECT id FROM requests WHERE status = 'queued'{filters}"
             f" ORDER BY priority DESC, rowid LIMIT 1) RETURNING {COLS}")
# The live lease a worker already holds, answered again instead of a second one (``lease(one_per_worker=True)``):
# its token unchanged, its expiry never shortened. The newest, should a worker hold several (leased before).
HELD_SQL = ("UPDATE requests SET lease_expires = MAX(lease_expires, ?), updated = ? WHERE id = (SELECT id FROM"
            " requests WHERE status = 'leased' AND worker_id = ? ORDER BY lease_expires DESC LIMIT 1)"
            f" RETURNING {COLS}")
RENEW_SQL = f"UPDATE requests SET lease_expires = ?, updated = ? WHERE {_LIVE} RETURNING id"
COMPLETE_SQL = ("UPDATE requests SET status = 'done', episode_id = ?, lease_expires = NULL, updated = ?"
                f" WHERE {_LIVE} RETURNING id")
RELEASE_SQL = (f"UPDATE requests SET status = 'queued', lease_expires = NULL, updated = ? WHERE {_LIVE}"
               f" RETURNING {COLS}")
# Ends a lease without an episode: one attempt more, dead once attempts reach max_attempts.
_END_SQL = ("UPDATE requests SET status = CASE WHEN attempts + 1 >= max_attempts THEN 'dead' ELSE 'queued' END,"
            " attempts = attempts + 1, last_error = ?, lease_expires = NULL, updated = ? WHERE {where}"
            f" RETURNING {COLS}")
FAIL_SQL = _END_SQL.format(where=_LIVE)
END_ONE_SQL = _END_SQL.format(where="id = ? AND status = 'leased'")
INSERT_SQL = ("INSERT INTO requests (id, created, updated, priority, task, shape, start_state, policy,"
              " policy_params, action_prefix, steps, reason, attempts, max_attempts, status,"
              f" idempotency_key) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 0, ?, 'queued', ?) RETURNING {COLS}")

# The live statuses counted from their partial indexes, the finished ones as the triggers keep them (``SCHEMA``);
# and all counted afresh from the rows: one count per partial index (each a covering scan of its own index, never
# of the table), linear in the history.
_LIVE_COUNTS = ("SELECT 'queued', COUNT(*) FROM requests WHERE status = 'queued' UNION ALL "
                "SELECT 'leased', COUNT(*) FROM requests WHERE status = 'leased' UNION ALL ")
COUNTS_SQL = _LIVE_COUNTS + "SELECT status, n FROM request_counts"
RECOUNT_SQL = _LIVE_COUNTS + f"SELECT status, COUNT(*) FROM requests WHERE status IN {TERMINAL_SQL} GROUP BY status"

_STATUS = {s.value: s for s in RequestStatus}
_loads = json.loads


def row_to_request(row: Sequence[Any]) -> Request:
    """A row of ``COLS`` (a ``SELECT`` or a ``RETURNING``) as a ``Request``."""
    (rid, created, updated, priority, task, shape, start_state, policy, policy_params, action_prefix, steps,
     reason, attempts, max_attempts, status, worker_id, token, lease_expires, last_error, idempotency_key,
     episode_id) = row
    return Request(rid, created, updated, priority, task, shape, _loads(start_state), policy, _loads(policy_params),
                   _loads(action_prefix), steps, _loads(reason), attempts, max_attempts, _STATUS[status],
                   worker_id, token, lease_expires, last_error, idempotency_key, episode_id)


_ENCODER = json.JSONEncoder(allow_nan=False, separators=(",", ":"))


def dumps(value: Any) -> str:
    """Compact JSON of a request's field; ``QueueError`` for a value JSON cannot hold (NaN, infinities, objects)."""
    try:
        return _ENCODER.encode(value)
    except (TypeError, ValueError) as exc:
        raise QueueError(f"expected JSON-encodable finite values, found {value!r:.80} ({exc})") from None
