"""Uploads in parts: the bytes of one episode sent as several ``NS/orch/upload`` queries, each answered.

Why: an episode sent as one Zenoh message holds the worker's link for its whole transfer. Over a slow uplink
its reply wait (the worker's ``--timeout``) had to cover the transfer, and the lease's renewals queued behind its
bytes, so the lease expired while it uploaded and the episode was dropped, or stored and never acknowledged.
A worker sends an episode bigger than its ``--upload-part-kb`` as parts (``messages.UploadPart``: the whole
upload's header plus the part's offset), one at a time: each waits for its answer, so a renewal waits behind one
part at most, and a lost reply or a link that drops costs one part, not the episode.

``PartStaging`` holds the parts received, in memory, per request: only for the lease's holder (the upload handler
checks the lease before a part is kept), one upload per request (a part of another upload of it, a new lease's or
other bytes, starts it again), and until its lease is not live any more and no part has come for ``max_age_s`` (a
worker that died mid-upload leaves nothing for long: the service's sweep every 5 minutes forgets it), and at
most ``max_total_bytes`` for every upload together, each counted at its whole size from its first part (a new
upload past that, once the parts of ended leases are forgotten, is answered ``unavailable``: the worker sends it
again later; one let in always gets its parts taken, so uploads under way never hold each other up for ever).
Another upload of other bytes under the same lease while one is in progress (two processes with one worker id) is
refused ``unavailable`` and logged as an error: each used to restart the other's for ever, the second's bytes
stored nowhere, nobody told why. A part is
answered with the bytes held from the start (``received``), from which the worker sends on: a part past them (the
service restarted and lost what it held) is not kept. The part that completes the bytes hands them, whole, to the
upload path every whole upload takes (sha256, verification, one ingest transaction), and are held until it has
stored or refused them for good (a store that failed for a reason that passes is tried again with the last part
alone): nothing of a partial upload is written to disk or indexed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from orchestrator.messages import UploadHeader, UploadPart
from orchestrator.protocol import ErrorCode, ProtocolError

log = logging.getLogger(__name__)


@dataclass
class _Partial:
    header: UploadHeader
    """The whole upload's header (request, token, worker, sha256, size)."""
    data: bytearray
    """Its bytes from the start, as far as received."""
    touched: float
    """When its last part came (``PartStaging``'s clock)."""


class PartStaging:
    """The parts of uploads in progress, by request; thread-safe (the upload handler's threads share it)."""

    def __init__(self, max_age_s: float, clock: Callable[[], float] = time.monotonic,
                 live: Callable[[UploadHeader], bool] = lambda header: False,
                 max_total_bytes: int | None = None, replace_after_s: float | None = None) -> None:
        self.max_age_s = max_age_s
        self.max_total_bytes = max_total_bytes
        """The most bytes set aside for all uploads in progress together, each its whole size from its first part
        on (None: no bound), so every upload let in can end; a new upload past it is answered ``unavailable`` (the
        worker sends it again after a backoff)."""
        self.replace_after_s = max_age_s / 4 if replace_after_s is None else replace_after_s
        """Another upload under the same lease (other sha256 or size) replaces the one held only once no part of
        that one has come for this long; before, it is refused: two processes share one worker id."""
        self._clock = clock
        self._live = live
        """Whether an upload's lease is still live (``sweep`` keeps those: a part may be slow to come)."""
        self._lock = threading.Lock()
        self._held: dict[str, _Partial] = {}

    def add(self, part: UploadPart, payload: bytes) -> int | bytes:
        """Keep ``payload`` at ``part.offset``. The number of bytes now held from the start (send on from there);
        the whole upload's bytes once they are all here, which stay held until ``drop`` (the caller's, once they
        are stored or refused for good: a store that failed for a reason that passes, or a repeat of the last part
        while it is stored, finds them whole again). Raises ProtocolError ``bad_field`` for a part that ends past
        the upload's size (nothing kept), ``unavailable`` for another upload under the lease of one still in
        progress (two processes with one worker id) and for a new upload whose size would take the bytes set
        aside past ``max_total_bytes`` (once the uploads whose lease ended are forgotten)."""
        end = part.offset + len(payload)
        if not payload or end > part.size:
            raise ProtocolError(ErrorCode.BAD_FIELD, f"payload: expected 1 to {part.size - part.offset} bytes "
                                f"(offset {part.offset} of size {part.size}), found {len(payload)}")
        try:
            return self._add(part, payload, end)
        except _Full:
            self.sweep(idle_s=0.0)  # an ended lease's parts go now, not at the next periodic sweep
        try:
            return self._add(part, payload, end)
        except _Full as full:
            log.warning("upload parts: %d bytes set aside for uploads in progress, at most %d: %s's upload of %d "
                        "bytes waits", full.promised, self.max_total_bytes, part.request_id, part.size)
            raise ProtocolError(ErrorCode.UNAVAILABLE, f"upload {part.request_id}: the service has {full.promised} "
                                f"bytes set aside for uploads in parts, at most {self.max_total_bytes}: send this "
                                "part again later") from None

    def _add(self, part: UploadPart, payload: bytes, end: int) -> int | bytes:
        whole = part.whole()
        with self._lock:
            now = self._clock()
            held = self._held.get(part.request_id)
            if held is not None and held.header != whole and _same_lease(held.header, whole) \
                    and now - held.touched < self.replace_after_s:
                log.error("two uploads of other bytes under one lease of %s (token %d): two workers use the id %s; "
                          "give each its own --id", whole.request_id, whole.token, whole.worker_id)
                raise ProtocolError(ErrorCode.UNAVAILABLE, f"upload {whole.request_id}: another upload of other "
                                    f"bytes under this lease (token {whole.token}) is in progress: two workers "
                                    f"share the id {whole.worker_id}? give each its own --id")
            if held is None or held.header != whole:  # a new upload of this request: a new lease's, other bytes
                if self.max_total_bytes is not None:  # its whole size is set aside: an upload let in always ends
                    promised = sum(p.header.size for r, p in self._held.items() if r != part.request_id)
                    if promised + whole.size > self.max_total_bytes:
                        raise _Full(promised)
                held = self._held[part.request_id] = _Partial(whole, bytearray(), now)
            held.touched = now
            if part.offset > len(held.data):  # a gap: what came before it is not here (lost by a restart)
                return len(held.data)
            held.data[part.offset:end] = payload  # a repeat of a part overwrites it with the same bytes
            return len(held.data) if len(held.data) < part.size else bytes(held.data)

    def drop(self, header: UploadHeader) -> None:
        """Forget the parts of ``header``'s upload (refused: its lease is not live any more, or it was stored)."""
        with self._lock:
            held = self._held.get(header.request_id)
            if held is not None and held.header == header:
                del self._held[header.request_id]

    def held_bytes(self) -> int:
        """Bytes held for uploads in progress (for tests and diagnostics)."""
        with self._lock:
            return sum(len(p.data) for p in self._held.values())

    def sweep(self, idle_s: float | None = None) -> None:
        """Forget the uploads no part has come for in ``idle_s`` (default ``max_age_s``) whose lease is not live any
        more (the service's sweeps call it; a live one's next part may be slow to come over a slow link)."""
        idle_s = self.max_age_s if idle_s is None else idle_s
        with self._lock:
            now = self._clock()
            old = [(r, p.header) for r, p in self._held.items() if now - p.touched > idle_s]
        for request_id, header in old:  # (the lease is looked up outside the lock: the database may be slow)
            if not self._live(header):
                self.drop(header)


class _Full(Exception):
    """A new upload's size would take the bytes set aside past ``PartStaging.max_total_bytes``."""

    def __init__(self, promised: int) -> None:
        super().__init__(promised)
        self.promised = promised


def _same_lease(a: UploadHeader, b: UploadHeader) -> bool:
    """Whether two uploads' headers name one lease (request, token, worker), whatever bytes they send."""
    return (a.request_id, a.token, a.worker_id) == (b.request_id, b.token, b.worker_id)
