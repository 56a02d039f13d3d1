"""Sending one episode's bytes: as one upload, or, when bigger than a part, as parts (``orchestrator.upload_parts``
says why), each answered before the next goes, the service saying from where to send on.

Imports only the wire contract (``orchestrator.messages``, ``protocol``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from orchestrator import messages
from orchestrator.protocol import MAX_UPLOAD_BYTES, ErrorCode, ProtocolError

log = logging.getLogger("workers.agent")

#: Default ``--upload-part-kb``: an episode of 50 steps at 64 px (~40 kB) goes whole, one of 1000 (~660 kB) in six
#: parts; one part takes ~4 s over a 30 kB/s uplink, well inside the reply wait and a renewal's interval.
DEFAULT_PART_KB = 128
#: Largest ``--upload-part-kb``: one part as big as the biggest upload.
MAX_PART_KB = MAX_UPLOAD_BYTES // 1024

#: ``send(payload, attachment) -> reply body``: one upload query (raises what ``Worker._call`` raises).
Send = Callable[[bytes, bytes], dict[str, Any]]


class EpisodeUpload:
    """The bytes of one episode and how far the service holds them. ``send_with(send)`` sends the rest and
    returns the reply that stored it (or says it was stored before); it raises what ``send`` raises, and is
    called again (by the worker's retries) to go on from the last part the service said it holds."""

    def __init__(self, data: bytes, request_id: str, token: int, worker_id: str, part_bytes: int | None) -> None:
        self.data = data
        self.header = messages.UploadHeader.for_payload(data, request_id=request_id, token=token, worker_id=worker_id)
        self.part_bytes = part_bytes or len(data)
        self.in_parts = len(data) > self.part_bytes
        """False: one upload of the whole (``part_bytes`` None, or once a service that takes no parts refused the
        first)."""
        self.no_parts_here = False
        """The service refused the first part as an older one does: the worker sends its next episodes whole."""
        self.held = 0
        """Bytes from the start the service said it holds."""

    def send_with(self, send: Send) -> dict[str, Any]:
        if not self.in_parts:
            return send(self.data, self.header.to_json())
        while True:
            start = self.held
            part = self.data[start:start + self.part_bytes]
            try:
                body = send(part, messages.UploadPart.of(self.header, start).to_json())
            except ProtocolError as exc:
                if exc.code is ErrorCode.BAD_FIELD and "unknown field(s) 'offset'" in exc.message:
                    log.warning("the service takes no upload in parts (an older version): %s goes whole "
                                "(%d bytes)", self.header.request_id, len(self.data))
                    self.in_parts, self.no_parts_here = False, True
                    return send(self.data, self.header.to_json())
                raise
            if "received" not in body:  # stored (or a duplicate of what was): the reply of a whole upload
                return body
            self.held = self._received(body.get("received"))
            if self.held <= start:  # not taken (the service lost what it held: a restart): go on after a backoff
                raise ProtocolError(ErrorCode.INTERNAL, f"upload of {self.header.request_id}: the part at byte "
                                    f"{start} was not kept; the service holds {self.held} bytes, sending from there")

    def _received(self, value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(self.data):
            self.held = 0  # a reply to distrust: from the start again
            raise ProtocolError(ErrorCode.INTERNAL, f"upload of {self.header.request_id}: expected the bytes held "
                                f"(0 to {len(self.data) - 1}), found {value!r:.40}; sending from the start")
        return value
