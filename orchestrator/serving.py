"""Serving queries: a queryable whose handler answers each query exactly once (``Server``).

A leaf of the wire plumbing like ``orchestrator.transport`` (its only import of ours), so a worker-side test
peer can serve too. Two things of zenoh-python 1.x shape it: a query's final reply is sent when the
``zenoh.Query`` is dropped (so every query is dropped right after its reply), and Zenoh's callbacks outlive
``undeclare()`` and ``session.close()`` (so ``Server.close`` waits for those in hand itself).
"""

from __future__ import annotations

import logging
import queue as queue_mod
import threading
import time
from collections.abc import Callable

import zenoh

from orchestrator.transport import ERROR_ENCODING, Incoming, Response, TransportError, default_error_body

log = logging.getLogger(__name__)

Handler = Callable[[Incoming], Response]


class Server:
    """A queryable whose queries are handled by a pool of Python threads.

    The Zenoh callback only enqueues the query, so slow handlers (SQLite, fsync) never block Zenoh's own threads.
    ``threads=0`` answers in the callback itself instead: no hand-off, for handlers that take well under a
    millisecond. Every query gets exactly one reply and is dropped right after it: ``handler``'s ``Response``; if
    the handler raised, an ordinary reply with body ``error_body("internal", why)`` (the crash is logged with its
    traceback and the server stays up); if the key is a pattern (``*``), which has no concrete key to reply on, an
    error reply with body ``error_body("bad_field", why)`` (``RemoteError`` for :func:`request`).
    """

    def __init__(self, session: zenoh.Session, key_expr: str, handler: Handler, threads: int = 2,
                 error_body: Callable[[str, str], bytes] = default_error_body) -> None:
        if threads < 0:
            raise TransportError(f"threads must be >= 0, found {threads}")
        self.key_expr = key_expr
        self._handler = handler
        self._error_body = error_body
        self._queue: queue_mod.SimpleQueue[zenoh.Query | None] = queue_mod.SimpleQueue()
        self._threads = [threading.Thread(target=self._run, name=f"serve:{key_expr}:{i}", daemon=True)
                         for i in range(threads)]
        for t in self._threads:
            t.start()
        # (Zenoh's callbacks outlive undeclare() and session.close(): ``close`` itself must wait for them)
        self._closing, self._in_callback, self._idle = False, 0, threading.Condition()
        # threads=0 answers on Zenoh's callback thread: no hand-off, for handlers of a few hundred us.
        self._queryable = session.declare_queryable(key_expr, self._accept)

    def close(self, timeout: float = 30.0) -> None:
        """Undeclare the queryable, answer a query that still comes ``unavailable``, and let the queries in hand
        finish: the handler threads', and those being answered on Zenoh's threads (``threads=0``), which
        ``undeclare`` does not wait for; ``timeout`` s at most in all (an upload's ingest on a slow disk may take
        seconds). After it no handler of ours runs, or a warning says which are still running."""
        deadline = time.monotonic() + timeout
        with self._idle:
            self._closing = True
        try:
            self._queryable.undeclare()
        except zenoh.ZError as exc:  # the session may already be closed
            log.debug("undeclare %s: %s", self.key_expr, exc)
        for _ in self._threads:
            self._queue.put(None)
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        with self._idle:
            self._idle.wait_for(lambda: self._in_callback == 0, max(0.0, deadline - time.monotonic()))
            running = self._in_callback + sum(t.is_alive() for t in self._threads)
        if running:
            log.warning("closing %s: %d query(ies) still being answered after %g s", self.key_expr, running,
                        timeout)

    def _accept(self, q: zenoh.Query) -> None:
        """Zenoh's callback: the query to a handler thread, or answered here (``threads=0``); once closing,
        refused ``unavailable`` (ask again: the service is stopping), never handled."""
        with self._idle:
            closing = self._closing
            self._in_callback += not closing
        if closing:
            try:
                q.reply_err(self._error_body("unavailable", f"{self.key_expr} is stopping: ask again"),
                            encoding=ERROR_ENCODING)
            except zenoh.ZError:
                pass
            finally:
                q.drop()
            return
        try:
            if self._threads:
                self._queue.put(q)
            else:
                self._serve_one(q)
        finally:
            with self._idle:
                self._in_callback -= 1
                self._idle.notify_all()

    def _run(self) -> None:
        while True:
            q = self._queue.get()
            if q is None:
                return
            self._serve_one(q)

    def _serve_one(self, q: zenoh.Query) -> None:
        try:
            key = str(q.key_expr)
            if "*" in key or "$" in key:  # no concrete key to reply on: an error reply instead
                q.reply_err(self._error_body("bad_field", f"expected a concrete key, found the pattern "
                                             f"{key!r}"), encoding=ERROR_ENCODING)
                return
            response = self._answer(q)
            q.reply(key, response.payload, attachment=response.attachment)
        except zenoh.ZError as exc:  # the querier left or the session is closing
            log.debug("cannot reply on %s: %s", q.key_expr, exc)
        except Exception as exc:  # noqa: BLE001 -- a query that reached us is answered, and the thread lives
            log.exception("cannot answer %s", q.key_expr)
            try:  # an error reply: request() must not take silence for "nobody serving" and send it again
                q.reply_err(self._error_body("internal", f"{type(exc).__name__}: {exc}"), encoding=ERROR_ENCODING)
            except zenoh.ZError:
                pass
        finally:
            q.drop()  # sends the final reply now, not whenever Python collects it

    def _answer(self, q: zenoh.Query) -> Response:
        key = str(q.key_expr)
        payload = q.payload.to_bytes() if q.payload is not None else b""
        att = q.attachment.to_bytes() if q.attachment is not None else None
        try:
            return self._handler(Incoming(key, payload, att))
        except Exception as exc:  # noqa: BLE001 -- boundary: one bad query must not take the service down
            log.exception("handler for %s failed", key)
            return Response(self._error_body("internal", f"{type(exc).__name__}: {exc}"))
