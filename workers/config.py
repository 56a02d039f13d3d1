"""What ``activecollect worker`` decides: ``WorkerConfig``, checked as it is made.

Imports only the wire contract (``orchestrator.endpoints``, ``messages``, ``protocol``, ``transport``) and what
the worker's own modules need.
"""

from __future__ import annotations

import os
import re
import socket
from dataclasses import dataclass
from pathlib import Path

from orchestrator import endpoints, messages, protocol, transport
from orchestrator.protocol import Keys, ProtocolError
from storage.records import TRAINABLE_SIZES, trainable_size
from workers.flags import MAX_REALTIME
from workers.upload import DEFAULT_PART_KB, MAX_PART_KB


class WorkerError(Exception):
    """The worker could not start (bad config, Zenoh refused the session)."""


def default_worker_id() -> str:
    """``<host>-<pid>``, cut to the characters a key chunk may hold."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "-", f"{socket.gethostname()}-{os.getpid()}")[:128]


@dataclass
class WorkerConfig:
    """Everything ``activecollect worker`` decides."""

    worker_id: str = ""
    """Unique id (liveliness key NS/workers/<id>); '' picks <host>-<pid>."""
    namespace: str = "activecollect"
    """Prefix of every Zenoh key of the deployment."""
    mode: str = "peer"
    """Zenoh mode without a config file: peer or client."""
    listen: tuple[str, ...] = ()
    """Zenoh endpoints to listen on (usually none for a worker)."""
    connect: tuple[str, ...] = ()
    """Zenoh endpoints of the service or routers."""
    zenoh_config: Path | None = None
    """A Zenoh JSON5 config file, passed through unchanged."""
    tasks: tuple[str, ...] = ()
    """Tasks this worker can do; empty means any."""
    shapes: tuple[str, ...] = ()
    """Object shapes this worker can do; empty means any."""
    image_size: int = 64
    """Camera frame side in pixels when the grant names none (the service's catalog is still empty, and the
    first upload fixes the size of every later one): a size a model trains on (``trainable_size``)."""
    max_episodes: int | None = None
    """Exit after uploading this many episodes (None: run until stopped)."""
    once: bool = False
    """Handle at most one request, then exit; also exit at once if the service has no work for it."""
    realtime: float = 0.0
    """A slow-down, 0 to MAX_REALTIME: an episode lasts at least realtime * steps / CONTROL_HZ seconds
    (1 = a real robot's pace, 2 = half speed); 0 = flat out."""
    timeout_s: float = 10.0
    """How long one query waits for the service's reply."""
    idle_poll_s: float = 0.5
    """Wait between lease attempts while the queue has no work for this worker."""
    max_backoff_s: float = 5.0
    """Longest wait between retries of a query nobody answered."""
    part_bytes: int = DEFAULT_PART_KB * 1024
    """An episode bigger than this is uploaded in parts of this size (``workers.upload``)."""
    report_attempts: int = 8
    """Tries of a failure report nobody answers before giving up (the lease then expires on its own).
    An upload has no such limit: it is retried until the service answers, the lease is lost (or, while
    draining, one more lease term is over), or a second stop signal gives the request back."""

    def __post_init__(self) -> None:
        self.worker_id = self.worker_id or default_worker_id()
        self.listen, self.connect = tuple(self.listen), tuple(self.connect)
        self.tasks, self.shapes = tuple(self.tasks), tuple(self.shapes)
        try:
            self.keys = Keys(self.namespace)
            protocol.check_id("worker_id", self.worker_id)
            messages.LeaseRequest(worker_id=self.worker_id, tasks=list(self.tasks), shapes=list(self.shapes))
        except ProtocolError as exc:
            raise WorkerError(exc.message) from None
        if self.mode not in transport.MODES:
            raise WorkerError(f"mode: expected one of {transport.MODES}, found {self.mode!r}")
        if not trainable_size(self.image_size):
            raise WorkerError(f"image_size: expected {TRAINABLE_SIZES} pixels (what a model trains on), "
                              f"found {self.image_size}")
        if self.max_episodes is not None and self.max_episodes < 1:
            raise WorkerError(f"max_episodes: expected a positive integer (None: no limit), found {self.max_episodes}")
        if self.once and self.max_episodes not in (None, 1):  # (the old worker dropped the N without a word)
            raise WorkerError(f"max_episodes: expected 1 with --once (it handles at most one request), "
                              f"found {self.max_episodes}")
        if not 0 <= self.realtime <= MAX_REALTIME:  # nan fails too; inf would overflow the wait in _pace
            raise WorkerError(f"realtime: expected a number from 0 (flat out) to {MAX_REALTIME:g}, "
                              f"found {self.realtime!r}")
        for name in ("timeout_s", "idle_poll_s", "max_backoff_s"):
            value = getattr(self, name)
            if not 0 < value <= endpoints.MAX_TIMEOUT_S:  # a wait longer than a day is a mistake, inf an overflow
                raise WorkerError(f"{name}: expected seconds in (0, {endpoints.MAX_TIMEOUT_S:g}], found {value!r}")
        if not 1024 <= self.part_bytes <= MAX_PART_KB * 1024:
            raise WorkerError(f"part_bytes: expected 1 to {MAX_PART_KB} kB, found {self.part_bytes / 1024:g} kB")
        if self.report_attempts < 1:
            raise WorkerError(f"report_attempts: expected >= 1, found {self.report_attempts}")
