"""A worker's hold on one leased request: renewed every lease_s / 3 on its own thread, how long it lasts, and
how long a draining worker may still try to upload.

Imports only the wire contract (``orchestrator.messages``, ``protocol``, ``transport``) and Zenoh.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from orchestrator import messages, transport
from orchestrator.messages import LeaseGrant
from orchestrator.protocol import ErrorCode, ProtocolError

log = logging.getLogger("workers.agent")

WARN_EVERY_S = 5.0
"""A run of failed renewals is logged at most this often (each one at the default 30 s lease: they go 10 s apart)."""


class Renewer:
    """Renews one lease every lease_s / 3 on its own thread until stopped; notes when it is lost.

    ``call(key, message, timeout)`` sends one renewal and raises ``TransportError`` (nobody
    answered) or ``ProtocolError`` (refused). Started at once: construct it when the grant arrives.
    """

    def __init__(self, call: Callable[[str, bytes, float], dict[str, Any]], key: str, grant: LeaseGrant,
                 worker_id: str) -> None:
        self._call, self._key, self._grant = call, key, grant
        self._msg = messages.RenewRequest(request_id=grant.request_id, token=grant.token,
                                          worker_id=worker_id).to_json()
        self._worker_id = worker_id
        self._done_by_this_id = f" is done with token {grant.token} held by {worker_id}"
        """How the service's refusal ends when another process with this id completed the request under this lease
        (``RequestQueue._stale``'s words)."""
        self._stop = threading.Event()
        self.lost: str | None = None
        """Why the lease is not ours any more (the service said so), or None."""
        self.uploading = False
        """Set once the episode's upload went out: a renewal refused from then on may only have met the request
        that upload completed (its reply still on the way), so it is said at INFO and the upload's reply decides."""
        self._until = time.monotonic() + grant.lease_s
        self._drain_until: float | None = None
        self._failures = 0
        """Renewals failed since the last one answered."""
        self._warned_at: float | None = None
        self._warned_failures = 0
        """``_failures`` as the last WARNING of a run said it."""
        self._thread = threading.Thread(target=self._run, name=f"renew:{grant.request_id}", daemon=True)
        self._thread.start()

    def remaining(self) -> float:
        """Seconds until the lease runs out by this worker's clock: lease_s after the sending of the last
        renewal the service acknowledged (or after the grant); <= 0 once it has."""
        return self._until - time.monotonic()

    def drain_left(self) -> float:
        """Seconds a draining worker may still try to upload: what is left of the lease, and of one lease term
        from the first call or the last part the service took (``drain_progress``), however often the service
        renews the lease meanwhile (a live service that renews it
        but will not store the episode, ``unavailable``, must not hold a draining worker for ever); <= 0 once
        either has run out. Renewals go on: the request stays this worker's while it tries."""
        now = time.monotonic()
        if self._drain_until is None:
            self._drain_until = now + self._grant.lease_s
        return min(self._until, self._drain_until) - now

    def drain_progress(self) -> None:
        """The service took more of the episode (a part acknowledged): a draining worker's term starts again from
        now. A slow uplink is not a service that will not store: only a term without progress ends the drain."""
        if self._drain_until is not None:
            self._drain_until = time.monotonic() + self._grant.lease_s

    def _run(self) -> None:
        try:
            self._renew()
        finally:
            if self._failures > self._warned_failures:  # a run's count since its last WARNING was never said
                log.info("renew %s: %d failed in a row when renewals stopped%s", self._grant.request_id,
                         self._failures, " (the lease was lost)" if self.lost is not None else "")

    def _renew(self) -> None:
        # By the clock, not after each call: a renewal nobody answered must not push the next one
        # back; and one call waits at most one interval, so two more tries fit in the lease.
        interval = max(self._grant.lease_s / 3.0, 0.01)
        due = time.monotonic() + interval
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due = max(due + interval, time.monotonic())
            sent = time.monotonic()
            try:
                self._call(self._key, self._msg, interval)
            except transport.TransportError as exc:  # transient: try again next tick
                self._failed("renew %s: %s", exc)
                continue
            except zenoh.ZError:
                if self._stop.is_set():  # the worker gave its request back and closed the session under us
                    return
                raise
            except ProtocolError as exc:
                if exc.code in (ErrorCode.STALE_TOKEN, ErrorCode.UNKNOWN_REQUEST):
                    self.lost = exc.message
                    if not self.uploading and exc.message.endswith(self._done_by_this_id):
                        log.error("lease of %s lost: the request was completed under this very lease (token %d) by "
                                  "an upload from the id %s, which this worker has not sent: two workers share the "
                                  "id %s and collect every request twice; give each its own --id",
                                  self._grant.request_id, self._grant.token, self._worker_id, self._worker_id)
                    elif self.uploading:
                        log.info("renewal of %s refused (%s) while its upload is out (which may have completed it: "
                                 "the upload's reply says): %s", self._grant.request_id, exc.code.value, exc.message)
                    else:
                        log.warning("lease of %s lost (%s): %s", self._grant.request_id, exc.code.value, exc.message)
                    return
                self._failed("renew %s refused: %s", exc)
                continue
            self._until = sent + self._grant.lease_s  # (the service extended it after we sent)
            if self._failures:
                log.info("renew %s answered again after %d failed", self._grant.request_id, self._failures)
                self._failures, self._warned_at, self._warned_failures = 0, None, 0

    def _failed(self, what: str, exc: Exception) -> None:
        """One renewal that failed (unanswered, or refused but for a lost lease): a WARNING for the first of a run
        of them, then at most one every ``WARN_EVERY_S`` with the count (at ``--lease-s 0.05`` a lost service made
        60 lines a second)."""
        self._failures += 1
        now = time.monotonic()
        if self._warned_at is None or now - self._warned_at >= WARN_EVERY_S:
            self._warned_at, self._warned_failures = now, self._failures
            more = f" ({self._failures} failed in a row)" if self._failures > 1 else ""
            log.warning(what + "%s", self._grant.request_id, exc, more)

    def stop(self, wait: bool = True, timeout: float | None = None) -> None:
        """No more renewals; ``wait``: also for one in flight, ``timeout`` seconds at most (a worker giving its
        request back at once does not wait, a stopping one not long: the thread is a daemon)."""
        self._stop.set()
        if wait:
            self._thread.join(timeout)
