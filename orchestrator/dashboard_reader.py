"""How the dashboard reads a request: by a deadline for the whole of it, and at most ``MAX_REQUEST_BYTES``.

``http.server`` bounds each read by the socket's timeout and each header line's length; a client trickling a byte
at a time, or sending a hundred long header lines, passed both.
"""

from __future__ import annotations

import http.client
import io
import math
import socket
import time
from typing import Any


#: The header bytes a request may send past what its request line may take. The base class bounds only each line
#: (64 KiB) and their number (100): 6.4 MB a connection, a few hundred MB of the serving process (the service's,
#: under `serve`) for 32.
MAX_HEADER_BYTES = 64 * 1024
#: What a connection may send in all, its request line and headers together (~136 KiB): the line's allowance (the
#: base class's 64 KiB, answered 414 past it), what the reader buffers past it, and ``MAX_HEADER_BYTES``; past it
#: the request is answered 431. (A short request line leaves its allowance to the headers.)
MAX_REQUEST_BYTES = 65537 + io.DEFAULT_BUFFER_SIZE + MAX_HEADER_BYTES


class DeadlineReader(io.RawIOBase):
    """The reading side of a socket whose every read ends by ``deadline`` (``time.monotonic()``), and that
    gives at most ``MAX_REQUEST_BYTES`` in all.

    The socket's own timeout bounds each read; a client sending a byte every few seconds
    would pass each one. Writes keep the socket's timeout.
    """

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.deadline = math.inf
        self._left = MAX_REQUEST_BYTES

    def readable(self) -> bool:
        return True

    def readinto(self, buf: Any) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the client did not send its request in time")
        if self._left <= 0:  # the base class answers it 431, as for a header line too long
            raise http.client.HTTPException(f"the request's line and headers are over {MAX_REQUEST_BYTES} bytes")
        per_read = self._sock.gettimeout()
        self._sock.settimeout(left if per_read is None else min(left, per_read))
        try:
            with memoryview(buf) as view:
                n = self._sock.recv_into(view[:self._left])
            self._left -= n
            return n
        finally:
            self._sock.settimeout(per_read)
