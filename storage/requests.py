"""A collection request as the queue stores it, and its lifecycle.

The records (``NewRequest`` in, ``Request`` and ``Lease`` out), the statuses and the
state machine ``TRANSITIONS`` that ``storage.queue.RequestQueue`` enforces: the only
legal moves are listed there (see the queue's docstring for the diagram).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from enum import Enum
from typing import Any

from storage.errors import NotFoundError, QueueError


class RequestStatus(str, Enum):
    """Where a request is in its lifecycle."""

    QUEUED = "queued"
    LEASED = "leased"
    DONE = "done"
    DEAD = "dead"
    CANCELLED = "cancelled"


class UnknownRequestError(QueueError, NotFoundError):
    """No request has this id."""


class IllegalTransitionError(QueueError):
    """The request's status does not allow the operation (e.g. cancel a done request)."""


_Q, _L, _D, _X, _C = (RequestStatus.QUEUED, RequestStatus.LEASED, RequestStatus.DONE,
                      RequestStatus.DEAD, RequestStatus.CANCELLED)

#: The state machine: action -> (statuses it may start from, statuses it may end in).
TRANSITIONS: dict[str, tuple[frozenset[RequestStatus], frozenset[RequestStatus]]] = {
    "lease": (frozenset({_Q}), frozenset({_L})),
    "renew": (frozenset({_L}), frozenset({_L})),
    "complete": (frozenset({_L}), frozenset({_D})),
    "fail": (frozenset({_L}), frozenset({_Q, _X})),
    "expire": (frozenset({_L}), frozenset({_Q, _X})),
    "worker_lost": (frozenset({_L}), frozenset({_Q, _X})),
    "release": (frozenset({_L}), frozenset({_Q})),
    "cancel": (frozenset({_Q, _L}), frozenset({_C})),
    "retry": (frozenset({_X, _C}), frozenset({_Q})),
    "prioritize": (frozenset({_Q, _L, _X, _C}), frozenset({_Q, _L, _X, _C})),
}

#: Actions that belong to the live lease: a wrong token / worker is a StaleLeaseError.
_LEASE_ACTIONS = frozenset({"renew", "complete", "fail", "release"})


def check_transition(action: str, current: RequestStatus, target: RequestStatus) -> None:
    """Raise IllegalTransitionError unless ``action`` may move a request from ``current`` to ``target``."""
    sources, targets = TRANSITIONS[action]
    if current not in sources or target not in targets:
        raise IllegalTransitionError(
            f"{action}: expected a request in status {'/'.join(sorted(s.value for s in sources))}, "
            f"found {current.value}")


def finite_number(name: str, value: Any, positive: bool = False) -> float:
    """``value`` as a float; ``QueueError`` unless it is a finite number (and > 0 when ``positive``).

    SQLite stores NaN as NULL: a NaN priority or lease expiry would fail far from its cause
    (a NOT NULL constraint) or, worse, never compare as expired.
    """
    try:
        number = float(value) if not isinstance(value, (bool, str, bytes)) else math.nan
    except (TypeError, ValueError):
        number = math.nan
    if not math.isfinite(number) or (positive and number <= 0):
        raise QueueError(f"{name}: expected a finite number{' > 0' if positive else ''}, found {value!r}")
    return number


@dataclass
class NewRequest:
    """What a planner or an operator asks to be collected (task-space checks live in orchestrator.protocol)."""

    task: str
    """Task family, e.g. ``push``."""
    shape: str
    """Object shape."""
    start_state: dict[str, Any]
    """Simulator state to reset to (``SimState.to_dict`` form)."""
    policy: str = "push"
    """Collection policy name."""
    policy_params: dict[str, Any] = field(default_factory=dict)
    """Parameters of the policy."""
    action_prefix: list[list[float]] = field(default_factory=list)
    """Actions replayed from the start state before the policy takes over."""
    steps: int = 50
    """Episode length asked for."""
    priority: float = 0.0
    """Higher is leased first."""
    reason: dict[str, Any] = field(default_factory=dict)
    """Why it exists: model_version, score, source_episode, step, planner."""
    max_attempts: int = 3
    """Unsuccessful leases allowed before the request is dead."""
    idempotency_key: str | None = None
    """Enqueueing twice with the same key returns the first request."""

    def __post_init__(self) -> None:
        for name in ("task", "shape", "policy"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise QueueError(f"{name}: expected a non-empty string, found {getattr(self, name)!r}")
        for name in ("start_state", "policy_params", "reason"):
            if not isinstance(getattr(self, name), dict):
                raise QueueError(f"{name}: expected a dict, found {type(getattr(self, name)).__name__}")
        if not isinstance(self.steps, int) or self.steps < 1:
            raise QueueError(f"steps: expected an integer >= 1, found {self.steps!r}")
        if not isinstance(self.max_attempts, int) or self.max_attempts < 1:
            raise QueueError(f"max_attempts: expected an integer >= 1, found {self.max_attempts!r}")
        self.priority = finite_number("priority", self.priority)
        if self.idempotency_key is not None and not isinstance(self.idempotency_key, str):
            raise QueueError(f"idempotency_key: expected a string or None, found {self.idempotency_key!r}")


@dataclass
class Request:
    """One stored request, as read from the queue."""

    id: str
    created: float
    updated: float
    priority: float
    task: str
    shape: str
    start_state: dict[str, Any]
    policy: str
    policy_params: dict[str, Any]
    action_prefix: list[list[float]]
    steps: int
    reason: dict[str, Any]
    attempts: int
    """Leases that ended without an episode since the last retry."""
    max_attempts: int
    status: RequestStatus
    worker_id: str | None
    """Worker holding (or, once done, last holding) the lease."""
    token: int
    """Fencing token of the latest lease (0 before the first lease)."""
    lease_expires: float | None
    last_error: str | None
    idempotency_key: str | None
    episode_id: str | None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (status as its string)."""
        out = asdict(self)
        out["status"] = self.status.value
        return out


@dataclass
class Lease:
    """A granted lease: the request, its fencing token and when it expires."""

    request: Request
    token: int
    expires_at: float
    again: bool = False
    """The worker already held this lease (``RequestQueue.lease(one_per_worker=True)``): answered again, same token."""
