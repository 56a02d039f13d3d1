"""The service's log line for a refused query, at most one a window per (key, code, worker).

A client refused again and again (an older worker of another frame size, refused every lease and asking twice a
second; a misconfigured or hostile one) would write a line per query, ~170,000 a day. The first refusal of each
kind is logged; later ones within ``window_s`` are counted, and the next line after the window says how many
there were: the next refusal's, or the service reaper's once the window is over (``flush``), or at stop.
``refusals_total`` (``orchestrator.metrics``) counts every one regardless.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

from orchestrator import protocol
from orchestrator.bounded import remember
from orchestrator.protocol import ProtocolError
from orchestrator.transport import Incoming

WINDOW_S = 60.0
"""At most one line per (key, code, worker) this often."""

MAX_PARSED_BYTES = 4096
"""A refused query's body (or upload header) longer than this is not read for its worker id."""

KINDS_MAX = 4096
"""The most (key, code, worker) kinds a ``RefusalLog`` keeps in memory, the oldest forgotten first (a forgotten kind
is logged afresh): a bound against any peer, which chooses the keys and worker ids it is refused for."""


class RefusalLog:
    """Logs refused queries on ``log`` (info), rate-limited; thread-safe. The (key, code, worker) kinds it keeps
    are bounded (``KINDS_MAX``). ``flush``, called every reap and at stop, says the count of a kind whose client
    was refused no more: it was said only when a later refusal of the kind came."""

    def __init__(self, log: logging.Logger, clock: Callable[[], float] = time.monotonic,
                 window_s: float = WINDOW_S) -> None:
        self._log, self._clock, self._window_s = log, clock, window_s
        self._kinds: OrderedDict[tuple[str, str, str], tuple[float, int, str]] = OrderedDict()
        """(key, code, worker) -> (``clock`` at its last line, refusals not logged since, the last one's text)."""
        self._lock = threading.Lock()

    def refused(self, msg: Incoming, exc: ProtocolError) -> None:
        """Note one refusal of ``msg``: a line now, or a count for the next one."""
        worker = claimed_worker(msg)
        kind, now = (msg.key, exc.code.value, worker), self._clock()
        text = protocol.one_line(str(exc))  # peer text: no forged lines
        with self._lock:
            last = self._kinds.get(kind)
            if last is not None and now - last[0] < self._window_s:
                self._kinds[kind] = (last[0], last[1] + 1, text)
                return
            remember(self._kinds, kind, (now, 0, text), KINDS_MAX)
        if last is not None and last[1]:
            self._log.info("refused %s%s: %s (and %d more like it in the %.0f s since the last such line)",
                           msg.key, _who(worker), text, last[1], now - last[0])
        else:
            self._log.info("refused %s%s: %s", msg.key, _who(worker), text)

    def flush(self, everything: bool = False) -> None:
        """A line for each kind refused since its last line whose window is over (``everything``: each kind, as the
        service stops), with the count and the last one's text; the next refusal of it is counted afresh."""
        now = self._clock()
        with self._lock:
            due = [(kind, last) for kind, last in self._kinds.items()
                   if last[1] and (everything or now - last[0] >= self._window_s)]
            for kind, (_, _, text) in due:
                self._kinds[kind] = (now, 0, text)
        for (key, _, worker), (at, count, text) in due:
            self._log.info("refused %s%s %d more time(s) in the %.0f s since the last such line, the last: %s",
                           key, _who(worker), count, now - at, text)


def _who(worker: str) -> str:
    return f" from worker {worker}" if worker else ""  # (a valid id: no forged lines)


def claimed_worker(msg: Incoming) -> str:
    """The worker id a query claims (its upload header's, else its JSON body's), '' when none can be read. A peer's
    word, good for grouping log lines only."""
    for raw in (msg.attachment, msg.payload):
        if not raw or len(raw) > MAX_PARSED_BYTES:
            continue
        try:
            worker = protocol.decode(raw).get("worker_id")
            return protocol.check_id("worker_id", worker)
        except ProtocolError:  # not a message, or no valid id in it
            continue
    return ""
