"""The admin operations behind ``NS/admin/**``: pure functions over the queue, catalog and registry.

No Zenoh here: the service decodes the query, calls :func:`serve` (or :func:`handle`) and sends
the bytes back; the operator CLI and the dashboard read the same reply bodies. Every refusal is a
``ProtocolError`` whose code says what kind of refusal it is (bad_field, unknown_request,
illegal_transition, unknown_op, ...).
"""

from __future__ import annotations

import dataclasses
import math
import sqlite3
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from orchestrator import protocol
from orchestrator.metrics import SPLITS  # the splits ``stats`` counts episodes of
from orchestrator.messages import AdminRequest, Event, RequestSpec
from orchestrator.protocol import ErrorCode, EventKind, ProtocolError
from storage.database import disk_json, quarantine_bytes
from storage.errors import QueueClosedError, QueueError, StaleLeaseError, StorageError, StorageUnavailableError
from storage.models import ModelStatus
from storage.queue import RequestQueue
from storage.requests import IllegalTransitionError, NewRequest, Request, RequestStatus, UnknownRequestError
from workers.policies import check_policy_params

#: Most requests one ``queue.ls`` may ask for.
MAX_LIST = 200
#: What a request asks a worker to do: a second ``queue.add`` with the same idempotency key must ask for the
#: same, or it is refused (a retry is answered with the first request; a reused key is a mistake). Priority
#: and reason are left out: ``queue.prioritize`` may have changed the one, and the other only explains.
_SAME_ASK = ("task", "shape", "start_state", "policy", "policy_params", "action_prefix", "steps", "max_attempts")
#: Encoded bytes the rows of one ``queue.ls`` / ``models.ls`` / ``workers.ls`` reply may take: a request summary may
#: carry 16 KB each of reason, policy_params and start_state, so MAX_LIST of them would not fit in
#: MAX_MESSAGE_BYTES. What is left is for the counts and the envelope; rows past it are left out
#: and the reply says ``"truncated": true``.
LIST_BUDGET_BYTES = protocol.MAX_MESSAGE_BYTES - 16 * 1024

_ARGS: dict[str, tuple[set[str], set[str]]] = {
    # op: (required args, optional args)
    "queue.ls": (set(), {"status", "limit"}),
    "queue.show": ({"id"}, set()),
    "queue.add": ({f.name for f in dataclasses.fields(RequestSpec) if f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING},
                  {f.name for f in dataclasses.fields(RequestSpec)}),
    "queue.cancel": ({"id"}, set()),
    "queue.retry": ({"id"}, set()),
    "queue.prioritize": ({"id", "priority"}, set()),
    "workers.ls": (set(), set()),
    "stats": (set(), set()),
    "models.ls": (set(), {"status"}),
}
assert set(_ARGS) == set(protocol.ADMIN_OPS), "every admin op needs an argument spec"

#: Reason of a manual request that gives none.
_MANUAL_REASON = {"model_version": "", "score": None, "source_episode": "", "step": None, "planner": "manual"}

#: The event an admin op that changed something publishes.
_EVENTS: dict[str, EventKind] = {
    "queue.add": EventKind.REQUEST_QUEUED,
    "queue.cancel": EventKind.REQUEST_CANCELLED,
    "queue.retry": EventKind.REQUEST_RETRIED,
    "queue.prioritize": EventKind.REQUEST_PRIORITIZED,
}


def storage_failure(exc: StorageError) -> ErrorCode | None:
    """The wire code when the storage itself failed under a request, not the request: ``unavailable`` for a
    failure that passes (a full disk, a busy or read-only database: ask again later; the service's
    ``StorageHealth`` holds the leases meanwhile), ``internal`` for one raised from an ``OSError`` or
    ``sqlite3.Error`` that does not (a damaged file). None for a refusal of the request itself."""
    if isinstance(exc, StorageUnavailableError):
        return ErrorCode.UNAVAILABLE
    if isinstance(exc.__cause__, (OSError, sqlite3.Error)):
        return ErrorCode.INTERNAL
    return None


def protocol_error(exc: StorageError) -> ProtocolError:
    """The wire error for a refused queue operation (also used by the service's lease / renew / fail)."""
    if (failed := storage_failure(exc)) is not None:  # not the request's fault: never bad_field
        code = failed
    elif isinstance(exc, QueueClosedError):  # (the service is stopping: ask again)
        code = ErrorCode.UNAVAILABLE
    elif isinstance(exc, StaleLeaseError):
        code = ErrorCode.STALE_TOKEN
    elif isinstance(exc, UnknownRequestError):
        code = ErrorCode.UNKNOWN_REQUEST
    elif isinstance(exc, IllegalTransitionError):
        code = ErrorCode.ILLEGAL_TRANSITION
    elif isinstance(exc, QueueError):
        code = ErrorCode.BAD_FIELD
    else:
        code = ErrorCode.INTERNAL
    return ProtocolError(code, str(exc))


def finite(obj: Any) -> Any:
    """A copy with NaN / infinities replaced by None, so strict JSON can carry it (model metrics)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    return obj


def request_summary(request: Request) -> dict[str, Any]:
    """A request without its bulky fields (action prefix as a length, error cut to 200 chars)."""
    out = request.to_dict()
    out["prefix_steps"] = len(out.pop("action_prefix"))
    if out["last_error"] is not None:
        out["last_error"] = out["last_error"][:200]
    return finite(out)


def _check_args(op: str, args: Mapping[str, Any]) -> None:
    required, optional = _ARGS[op]
    missing = sorted(required - set(args))
    unknown = sorted(set(args) - required - optional)
    if missing or unknown:
        expected = ", ".join(sorted(required) + [f"[{o}]" for o in sorted(optional - required)]) or "no arguments"
        raise ProtocolError(ErrorCode.BAD_FIELD, f"{op}: expected {expected}; "
                            f"missing {missing or 'none'}, unknown {unknown or 'none'}")


def _int_arg(op: str, name: str, value: Any, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ProtocolError(ErrorCode.BAD_FIELD, f"{op}: {name} expected an integer in [{lo}, {hi}], "
                            f"found {value!r:.40}")
    return value


def _priority_arg(op: str, value: Any) -> float:
    return protocol.check_float(f"{op}: priority", value, -protocol.MAX_PRIORITY, protocol.MAX_PRIORITY)


def _status_arg(op: str, value: Any, choices: Iterable[str]) -> str | None:
    choices = tuple(choices)
    if value is None:
        return None
    if value not in choices:
        raise ProtocolError(ErrorCode.BAD_FIELD, f"{op}: status expected one of {', '.join(choices)}, "
                            f"found {value!r:.40}")
    return value


def _fit(rows: Iterable[dict[str, Any]], budget: int = LIST_BUDGET_BYTES) -> tuple[list[dict[str, Any]], bool]:
    """The leading ``rows`` whose JSON list stays within ``budget`` bytes; True when some were left out."""
    out: list[dict[str, Any]] = []
    used = 2  # the list's brackets
    for row in rows:
        used += len(protocol.encode(row)) + 1  # and its comma
        if used > budget:
            return out, True
        out.append(row)
    return out, False


def _worker_ids(workers: Callable[[], Iterable[str]] | None) -> list[str]:
    return sorted(set(workers())) if workers is not None else []


def _queue_op(op: str, args: Mapping[str, Any], queue: RequestQueue) -> dict[str, Any]:
    if op == "queue.ls":
        status = _status_arg(op, args.get("status"), (s.value for s in RequestStatus))
        limit = _int_arg(op, "limit", args.get("limit", 50), 1, MAX_LIST)
        rows, truncated = _fit(request_summary(r) for r in queue.list(status=status, limit=limit))
        counts = queue.counts()
        # total: how many match the status (limit aside); truncated: the byte budget cut the list short
        return {"requests": rows, "counts": counts, "truncated": truncated,
                "total": counts[status] if status is not None else sum(counts.values())}
    if op == "queue.add":
        spec = RequestSpec.from_dict({"reason": dict(_MANUAL_REASON), **args})
        try:  # what a worker would refuse after leasing it, again and again until the request is dead
            check_policy_params(spec.policy, spec.policy_params)
        except ValueError as exc:
            raise ProtocolError(ErrorCode.BAD_FIELD, f"policy_params: {exc}") from None
        request, created = queue.enqueue(NewRequest(**spec.to_dict()))
        if not created:
            _refuse_other_ask(spec, request)
        return {"request": request_summary(request), "created": created}
    request_id = protocol.check_id("id", args["id"])
    priority = _priority_arg(op, args["priority"]) if op == "queue.prioritize" else None
    request_id = queue.resolve(request_id)  # the arguments are good: now a unique prefix will do
    if op == "queue.show":
        return {"request": finite(queue.get(request_id).to_dict())}
    if op == "queue.cancel":
        return {"request": request_summary(queue.cancel(request_id))}
    if op == "queue.retry":
        return {"request": request_summary(queue.retry(request_id))}
    if op == "queue.prioritize":
        return {"request": request_summary(queue.prioritize(request_id, priority))}
    raise ProtocolError(ErrorCode.UNKNOWN_OP, f"expected a queue op, found {op!r}")  # pragma: no cover


def _refuse_other_ask(spec: RequestSpec, request: Request) -> None:
    """BAD_FIELD when ``request``, found by ``spec``'s idempotency key, asks for something else than ``spec``."""
    differ = [name for name in _SAME_ASK if getattr(spec, name) != getattr(request, name)]
    if differ:
        raise ProtocolError(ErrorCode.BAD_FIELD,
                            f"idempotency_key {spec.idempotency_key!r:.80} already names request {request.id}, "
                            f"which asks for another {', '.join(differ)}: use a new key for a new request "
                            f"(`queue show {request.id}` shows the first)")


def _workers_ls(queue: RequestQueue, workers: Callable[[], Iterable[str]] | None) -> dict[str, Any]:
    alive = set(_worker_ids(workers))
    leases: dict[str, list[str]] = {w: [] for w in alive}
    for request in queue.list(status=RequestStatus.LEASED):
        leases.setdefault(request.worker_id or "", []).append(request.id)
    rows = [{"id": w, "alive": w in alive, "leases": sorted(ids)} for w, ids in sorted(leases.items())]
    # when they do not all fit, those holding leases do first (a dead one's is a lease nobody renews)
    kept, truncated = _fit(sorted(rows, key=lambda row: not row["leases"]))
    return {"workers": sorted(kept, key=lambda row: row["id"]), "truncated": truncated, "total": len(rows)}


def _stats(queue: RequestQueue, catalog: Any, registry: Any,
           workers: Callable[[], Iterable[str]] | None) -> dict[str, Any]:
    episodes = disk = held = None
    if catalog is not None:
        episodes = {split: catalog.count(split=split) for split in SPLITS}
        episodes["total"] = catalog.count()
        episodes["quarantined"] = catalog.count(quarantined=True)
        disk = disk_json(catalog.data_dir)
        held = quarantine_bytes(catalog.data_dir)  # a walk, asked for by an operator (not on every scrape)
    champion = registry.champion() if registry is not None else None
    h1 = registry.get(champion).metrics.get("h1_mse") if champion is not None else None  # (the dashboard's too)
    return {"requests": queue.counts(), "episodes": episodes, "champion": champion, "champion_h1_mse": h1,
            "champion_problem": registry.weights_problem(champion) if champion is not None else None,
            "workers": len(_worker_ids(workers)), "disk": disk, "quarantine_bytes": held}


def _models_ls(args: Mapping[str, Any], registry: Any) -> dict[str, Any]:
    if registry is None:
        raise ProtocolError(ErrorCode.UNAVAILABLE, "models.ls: this service has no model registry")
    status = _status_arg("models.ls", args.get("status"), (s.value for s in ModelStatus))
    records = registry.list(status) if status is not None else registry.list()
    rows = []
    for rec in records:
        row = rec.to_json()
        row.pop("config", None)
        rows.append(finite(row))
    newest, truncated = _fit(reversed(rows))  # when they do not all fit, the newest do
    return {"models": newest[::-1], "champion": registry.champion(), "truncated": truncated,
            "total": len(rows)}


#: The admin ops that change the queue; the rest only read.
WRITE_OPS = frozenset({"queue.add", "queue.cancel", "queue.retry", "queue.prioritize"})


def handle(op: str, args: Mapping[str, Any] | None = None, *, queue: RequestQueue, catalog: Any = None,
           registry: Any = None, workers: Callable[[], Iterable[str]] | None = None) -> dict[str, Any]:
    """Run one admin op; returns the reply body (pass it to ``protocol.ok_reply``).

    catalog: a ``storage.catalog.Catalog`` (for ``stats``); registry: a ``storage.models.ModelRegistry``
    (``stats``, ``models.ls``); workers: returns the ids of the workers alive now.
    Raises ProtocolError: unknown_op, bad_field (bad arguments), unknown_request, illegal_transition.
    """
    request = AdminRequest(op=op, args=dict(args or {}))  # validates op and args' JSON-ness
    op, args = request.op, request.args
    _check_args(op, args)
    try:
        if op.startswith("queue."):
            return _queue_op(op, args, queue)
        if op == "workers.ls":
            return _workers_ls(queue, workers)
        if op == "stats":
            return _stats(queue, catalog, registry, workers)
        return _models_ls(args, registry)
    except StorageError as exc:
        raise protocol_error(exc) from exc


def serve(payload: bytes | None, *, op: str | None = None, queue: RequestQueue, catalog: Any = None,
          registry: Any = None, workers: Callable[[], Iterable[str]] | None = None) -> bytes:
    """Answer one admin query: ``payload`` is an AdminRequest (JSON) or empty; ``op`` the key's op.

    Returns the reply bytes: ok with the body, or an error reply (never raises ProtocolError).
    """
    try:
        if payload is None or len(payload) == 0:
            if op is None:
                raise ProtocolError(ErrorCode.BAD_JSON, "expected an AdminRequest, found no payload")
            request = AdminRequest(op=op)
        else:
            request = AdminRequest.from_json(payload)
            if op is not None and request.op != op:
                raise ProtocolError(ErrorCode.BAD_FIELD, f"op: expected {op!r} (the key's op), "
                                    f"found {request.op!r}")
        body = handle(request.op, request.args, queue=queue, catalog=catalog, registry=registry,
                      workers=workers)
        return protocol.ok_reply(**body)
    except ProtocolError as exc:
        return exc.reply()


def admin_event(op: str, body: Mapping[str, Any], at: float | None = None) -> Event | None:
    """The event a successful op publishes (queue.add / cancel / retry / prioritize), or None."""
    kind = _EVENTS.get(op)
    if kind is None or (op == "queue.add" and not body.get("created")):
        return None
    request = body["request"]
    data = {"request_id": request["id"], "status": request["status"], "priority": request["priority"],
            "shape": request["shape"], "source": "admin"}
    return Event(kind=kind.value, at=time.time() if at is None else at, data=data)
