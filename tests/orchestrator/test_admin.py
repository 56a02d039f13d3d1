"""Admin operations over a real queue and a real model registry in a tmp data dir."""

from __future__ import annotations

import errno
import json
import shutil
import sqlite3
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from orchestrator import admin, messages, protocol
from orchestrator.protocol import ErrorCode, ProtocolError
from storage.catalog import Catalog
from storage.errors import QueueClosedError, QueueError, QueueUnavailableError, StaleLeaseError, StorageError
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from storage.requests import IllegalTransitionError, NewRequest, UnknownRequestError

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.0]}
SPEC = {"task": "push", "shape": "box", "start_state": START, "policy": "push", "steps": 20,
        "priority": 1.5, "idempotency_key": "manual-1"}


@pytest.fixture
def queue(tmp_path: Path):
    q = RequestQueue(tmp_path / "catalog.sqlite")
    yield q
    q.close()


def call(op: str, args: dict | None = None, **kw) -> dict:
    return admin.handle(op, args, **kw)


def refused(code: ErrorCode, op: str, args: dict | None = None, **kw) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        admin.handle(op, args, **kw)
    assert info.value.code == code, info.value
    return info.value


def test_add_show_ls(queue: RequestQueue) -> None:
    body = call("queue.add", SPEC, queue=queue)
    assert body["created"] is True
    request = body["request"]
    assert request["status"] == "queued" and request["priority"] == 1.5 and request["reason"]["planner"] == "manual"
    again = call("queue.add", dict(SPEC, priority=9.0), queue=queue)
    assert again["created"] is False and again["request"]["id"] == request["id"]
    assert admin.admin_event("queue.add", again) is None
    shown = call("queue.show", {"id": request["id"]}, queue=queue)["request"]
    assert shown["start_state"]["object"] == [256.0, 256.0, 0.0] and shown["action_prefix"] == []
    listed = call("queue.ls", {"status": "queued"}, queue=queue)
    assert [r["id"] for r in listed["requests"]] == [request["id"]] and listed["counts"]["queued"] == 1
    assert call("queue.ls", {"status": "done"}, queue=queue)["requests"] == []
    assert len(call("queue.ls", queue=queue)["requests"]) == 1


@pytest.mark.parametrize("change", [{"shape": "T", "start_state": dict(START, shape="T")},
                                    {"start_state": dict(START, agent=[101.0, 100.0])}, {"steps": 21},
                                    {"policy": "random_waypoints"}, {"policy_params": {"noise": 3.0}},
                                    {"action_prefix": [[1.0, 0.0]]}, {"max_attempts": 5}])
def test_a_reused_idempotency_key_asking_for_another_request_is_refused(queue: RequestQueue, change: dict) -> None:
    first = call("queue.add", SPEC, queue=queue)["request"]
    err = refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, **change), queue=queue)
    assert f"already names request {first['id']}" in err.message
    assert err.message.split("another ")[1].startswith(", ".join(k for k in admin._SAME_ASK if k in change))
    assert [r.id for r in queue.list()] == [first["id"]] and queue.get(first["id"]).to_dict()["steps"] == 20
    # what only explains or orders the request may differ: a retry after a prioritize is still the same ask
    call("queue.prioritize", {"id": first["id"], "priority": 4.0}, queue=queue)
    again = call("queue.add", dict(SPEC, reason={"planner": "manual", "note": "retry"}), queue=queue)
    assert not again["created"] and again["request"]["id"] == first["id"] and again["request"]["priority"] == 4.0


def test_add_validates_through_the_protocol(queue: RequestQueue) -> None:
    # policy parameters a worker would refuse after every lease until the request is dead
    err = refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, policy_params={"side": "up"}), queue=queue)
    assert err.message.startswith("policy_params: policy 'push'") and "'up'" in err.message
    refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, policy_params={"sid": "left"}), queue=queue)
    refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, shape="hexagon"), queue=queue)
    refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, start_state=dict(START, agent=[600.0, 1.0])), queue=queue)
    refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, steps=protocol.MAX_EPISODE_STEPS + 1), queue=queue)
    refused(ErrorCode.BAD_FIELD, "queue.add", dict(SPEC, colour="red"), queue=queue)
    refused(ErrorCode.BAD_FIELD, "queue.add", {"task": "push"}, queue=queue)
    assert queue.counts()["queued"] == 0


def test_cancel_retry_prioritize(queue: RequestQueue) -> None:
    rid = call("queue.add", SPEC, queue=queue)["request"]["id"]
    body = call("queue.prioritize", {"id": rid, "priority": 7}, queue=queue)
    assert body["request"]["priority"] == 7.0
    event = admin.admin_event("queue.prioritize", body, at=5.0)
    assert event.kind == "request.prioritized" and event.data["request_id"] == rid
    assert messages.Event.from_json(event.to_json()) == event
    assert call("queue.cancel", {"id": rid}, queue=queue)["request"]["status"] == "cancelled"
    err = refused(ErrorCode.ILLEGAL_TRANSITION, "queue.cancel", {"id": rid}, queue=queue)
    assert "cancelled" in err.message
    assert call("queue.retry", {"id": rid}, queue=queue)["request"]["status"] == "queued"
    refused(ErrorCode.ILLEGAL_TRANSITION, "queue.retry", {"id": rid}, queue=queue)
    refused(ErrorCode.UNKNOWN_REQUEST, "queue.show", {"id": "nope"}, queue=queue)
    refused(ErrorCode.UNKNOWN_REQUEST, "queue.cancel", {"id": "nope"}, queue=queue)


def test_a_unique_id_prefix_names_a_request(queue: RequestQueue) -> None:
    ids = [call("queue.add", dict(SPEC, idempotency_key=f"k{i}"), queue=queue)["request"]["id"] for i in range(17)]
    first_chars = Counter(i[0] for i in ids)  # 17 hex ids: two share a first character
    shared = next(c for c, n in first_chars.items() if n > 1)
    err = refused(ErrorCode.UNKNOWN_REQUEST, "queue.cancel", {"id": shared}, queue=queue)
    assert "ambiguous" in err.message
    one = ids[0]
    prefix = next(one[:n] for n in range(1, len(one) + 1) if sum(i.startswith(one[:n]) for i in ids) == 1)
    assert call("queue.show", {"id": prefix}, queue=queue)["request"]["id"] == one
    assert call("queue.prioritize", {"id": prefix, "priority": 4}, queue=queue)["request"]["id"] == one
    assert call("queue.cancel", {"id": prefix}, queue=queue)["request"]["id"] == one
    err = refused(ErrorCode.UNKNOWN_REQUEST, "queue.show", {"id": "zz"}, queue=queue)
    assert "no request" in err.message
    assert queue.get(one).priority == 4.0 and [queue.get(i).status.value for i in ids].count("cancelled") == 1


def test_retry_a_dead_request(queue: RequestQueue) -> None:
    req, _ = queue.enqueue(NewRequest(task="push", shape="box", start_state=START, max_attempts=1))
    queue.fail(req.id, queue.lease("w1").token, "sim crashed")
    shown = call("queue.ls", {"status": "dead"}, queue=queue)["requests"][0]
    assert shown["id"] == req.id and shown["last_error"] == "sim crashed"
    assert call("queue.retry", {"id": req.id}, queue=queue)["request"]["attempts"] == 0
    assert queue.lease("w2").request.id == req.id


@pytest.mark.parametrize("op, args, code", [
    ("queue.drop", {}, ErrorCode.UNKNOWN_OP),
    ("", {}, ErrorCode.UNKNOWN_OP),
    ("queue.ls", {"status": "sleeping"}, ErrorCode.BAD_FIELD),
    ("queue.ls", {"limit": 0}, ErrorCode.BAD_FIELD),
    ("queue.ls", {"limit": admin.MAX_LIST + 1}, ErrorCode.BAD_FIELD),
    ("queue.ls", {"limit": "5"}, ErrorCode.BAD_FIELD),
    ("queue.ls", {"colour": "red"}, ErrorCode.BAD_FIELD),
    ("queue.show", {}, ErrorCode.BAD_FIELD),
    ("queue.show", {"id": "a/b"}, ErrorCode.BAD_FIELD),
    ("queue.show", {"id": 5}, ErrorCode.BAD_FIELD),
    ("queue.prioritize", {"id": "x"}, ErrorCode.BAD_FIELD),
    ("queue.prioritize", {"id": "x", "priority": "high"}, ErrorCode.BAD_FIELD),
    ("queue.prioritize", {"id": "x", "priority": True}, ErrorCode.BAD_FIELD),
    ("queue.prioritize", {"id": "x", "priority": 10 ** 400}, ErrorCode.BAD_FIELD),  # too large for a float
    ("queue.add", dict(SPEC, priority=10 ** 400), ErrorCode.BAD_FIELD),
    ("stats", {"x": 1}, ErrorCode.BAD_FIELD),
    ("models.ls", {}, ErrorCode.UNAVAILABLE),
])
def test_bad_ops_and_args(queue: RequestQueue, op: str, args: dict, code: ErrorCode) -> None:
    err = refused(code, op, args, queue=queue)
    assert err.message


def test_workers_and_stats(queue: RequestQueue, tmp_path: Path) -> None:
    for _ in range(3):
        queue.enqueue(NewRequest(task="push", shape="T", start_state=dict(START, shape="T")))
    held = queue.lease("w1")
    queue.lease("ghost")  # a lease whose worker is no longer alive (not reaped yet)
    body = call("workers.ls", queue=queue, workers=lambda: ["w2", "w1"])
    ghost = [r.id for r in queue.list(status="leased") if r.worker_id == "ghost"]
    assert body["workers"] == [
        {"id": "ghost", "alive": False, "leases": ghost},
        {"id": "w1", "alive": True, "leases": [held.request.id]},
        {"id": "w2", "alive": True, "leases": []},
    ]
    registry = ModelRegistry(tmp_path)
    stats = call("stats", queue=queue, registry=registry, workers=lambda: ["w1"])
    assert stats == {"requests": {"queued": 1, "leased": 2, "done": 0, "dead": 0, "cancelled": 0},
                     "episodes": None, "champion": None, "champion_h1_mse": None, "champion_problem": None,
                     "workers": 1, "disk": None,
                     "quarantine_bytes": None}


def test_stats_with_a_catalog(queue: RequestQueue, tmp_path: Path) -> None:
    catalog_mod = pytest.importorskip("storage.catalog")
    catalog = catalog_mod.Catalog(tmp_path)
    stats = call("stats", queue=queue, catalog=catalog)
    assert stats["episodes"] == {"train": 0, "eval": 0, "total": 0, "quarantined": 0}
    from tests.storage.test_episodes import make_episode
    rng = np.random.default_rng(0)
    _, lost = (catalog.add_episode(make_episode(rng)).episode_id for _ in range(2))
    catalog.quarantine(lost, "operator: wrong object")
    stats = call("stats", queue=queue, catalog=catalog)
    assert stats["episodes"] == {"train": 2, "eval": 0, "total": 2, "quarantined": 1}
    assert stats["disk"]["size_bytes"] == shutil.disk_usage(tmp_path).total and stats["disk"]["free_bytes"] > 0


def test_stats_say_when_the_champion_cannot_be_served(queue: RequestQueue, tmp_path: Path) -> None:
    registry = ModelRegistry(tmp_path)
    version = registry.register(b"weights" * 10, {}, {"h1_mse": 0.01}, snapshot_id="s", eval_split_hash="h")
    registry.promote(version)
    stats = call("stats", queue=queue, registry=registry)
    assert stats["champion_problem"] is None and stats["champion_h1_mse"] == 0.01  # (as the dashboard's /api/stats)
    registry.get(version).weights_path.unlink()
    problem = call("stats", queue=queue, registry=registry)["champion_problem"]
    assert problem == f"checkpoint {version}: weights file {registry.get(version).weights_path} is missing"


def test_models_ls(queue: RequestQueue, tmp_path: Path) -> None:
    registry = ModelRegistry(tmp_path)
    assert call("models.ls", queue=queue, registry=registry) == {"models": [], "champion": None,
                                                                 "truncated": False, "total": 0}
    version = registry.register(b"weights" * 10, {"members": 2}, {"h1_mse": 0.01, "spearman": float("nan")},
                                snapshot_id="snap-1", eval_split_hash="split-1")
    registry.promote(version)
    body = call("models.ls", queue=queue, registry=registry)
    assert body["champion"] == version and body["models"][0]["version"] == version
    assert body["models"][0]["metrics"] == {"h1_mse": 0.01, "spearman": None}  # NaN made JSON-safe
    protocol.ok_reply(**body)  # strict JSON (no NaN) must accept it
    assert call("models.ls", {"status": "candidate"}, queue=queue, registry=registry)["models"] == []


@pytest.mark.parametrize("status", [[], {}, "bogus", 3, "CHAMPION"])
def test_models_ls_refuses_a_bad_status_naming_the_choices(queue: RequestQueue, tmp_path: Path, status) -> None:
    err = refused(ErrorCode.BAD_FIELD, "models.ls", {"status": status}, queue=queue, registry=ModelRegistry(tmp_path))
    assert "candidate, champion, retired, rejected" in err.message


def _big(n: int) -> dict:
    """A reason / policy_params of about ``n`` encoded bytes (each may be up to MAX_OBJECT_BYTES)."""
    return {"note": "x" * (n - 20)}


def test_queue_ls_fits_in_one_message_and_says_when_cut(queue: RequestQueue) -> None:
    for _ in range(20):  # as a planner queues them (an admin queue.add's args stop at 16 KB in all)
        queue.enqueue(NewRequest(task="push", shape="box", start_state=START, reason=_big(15_000),
                                 policy_params=_big(15_000)))
    queue.enqueue(NewRequest(task="push", shape="box", start_state=START, priority=-1.0))  # a small one, last
    body = call("queue.ls", {"limit": admin.MAX_LIST}, queue=queue)
    reply = protocol.ok_reply(**body)
    assert len(reply) <= protocol.MAX_MESSAGE_BYTES
    assert protocol.parse_reply(reply)["truncated"] is True  # what every client reads back
    assert body["total"] == 21 and 0 < len(body["requests"]) < 21
    everything = [r.id for r in queue.list(limit=admin.MAX_LIST)]
    assert [r["id"] for r in body["requests"]] == everything[:len(body["requests"])]  # the leading rows, in order
    small = call("queue.ls", {"limit": 3}, queue=queue)
    assert small["truncated"] is False and len(small["requests"]) == 3 and small["total"] == 21
    only = call("queue.ls", {"status": "done"}, queue=queue)
    assert only == {"requests": [], "counts": queue.counts(), "truncated": False, "total": 0}


def test_models_ls_keeps_the_newest_models_that_fit(queue: RequestQueue, tmp_path: Path) -> None:
    registry = ModelRegistry(tmp_path)
    versions = [registry.register(b"w%d" % i, {"members": 2}, {"h1_mse": 0.1, "curve": [0.5] * 6000},
                                  snapshot_id="snap", eval_split_hash="split") for i in range(12)]
    body = call("models.ls", queue=queue, registry=registry)
    assert len(protocol.ok_reply(**body)) <= protocol.MAX_MESSAGE_BYTES
    assert body["truncated"] is True and body["total"] == 12
    kept = [row["version"] for row in body["models"]]
    assert kept and kept == versions[-len(kept):]  # the newest, still in registration order
    assert call("models.ls", {"status": "champion"}, queue=queue, registry=registry)["truncated"] is False


def test_serve_bytes(queue: RequestQueue) -> None:
    reply = admin.serve(messages.AdminRequest(op="queue.add", args=SPEC).to_json(), op="queue.add", queue=queue)
    body = protocol.parse_reply(reply)
    assert body["created"] is True
    assert protocol.parse_reply(admin.serve(b"", op="stats", queue=queue))["requests"]["queued"] == 1
    for payload, op, code in [
        (b"{oops", "stats", "bad_json"),
        (b'{"v": 9, "op": "stats"}', "stats", "bad_version"),
        (messages.AdminRequest(op="stats").to_json(), "queue.ls", "bad_field"),  # op disagrees with the key
        (b"", None, "bad_json"),
        (b'{"v": 1, "op": "stats", "args": {"a": ' + b"[" * 5000 + b"]" * 5000 + b"}}", "stats", "bad_json"),
        (messages.AdminRequest(op="queue.show", args={"id": "nope"}).to_json(), None, "unknown_request"),
    ]:
        answer = json.loads(admin.serve(payload, op=op, queue=queue))
        assert answer["ok"] is False and answer["error"] == code, answer


@pytest.mark.parametrize("exc, code", [
    (StaleLeaseError("x"), ErrorCode.STALE_TOKEN),
    (UnknownRequestError("x"), ErrorCode.UNKNOWN_REQUEST),
    (IllegalTransitionError("x"), ErrorCode.ILLEGAL_TRANSITION),
    (QueueError("x"), ErrorCode.BAD_FIELD),
    (QueueClosedError("x"), ErrorCode.UNAVAILABLE),  # the service is stopping: not the request's fault
    (StorageError("x"), ErrorCode.INTERNAL),
])
def test_protocol_error_mapping(exc: StorageError, code: ErrorCode) -> None:
    assert admin.protocol_error(exc).code == code


def test_a_closed_queue_refuses_as_closed(tmp_path) -> None:
    """What a handler still running as its service stops is told: ``unavailable`` on the wire (above), not
    ``bad_field``, which a worker would take for its own fault and fail the request."""
    queue = RequestQueue(tmp_path / "q.sqlite")
    queue.close()
    with pytest.raises(QueueClosedError, match="is closed"):
        queue.lease("w1")


def test_only_write_ops_change_the_database(queue: RequestQueue, tmp_path: Path) -> None:
    """The service lets every op outside WRITE_OPS run beside the writer: they must not write."""
    assert admin.WRITE_OPS < set(protocol.ADMIN_OPS)
    catalog, registry = Catalog(tmp_path), ModelRegistry(tmp_path)
    created = call("queue.add", SPEC, queue=queue)["request"]["id"]
    watcher = sqlite3.connect(tmp_path / "catalog.sqlite")
    version = lambda: watcher.execute("PRAGMA data_version").fetchone()[0]  # moves on another connection's commit
    args = {"queue.show": {"id": created}, "queue.cancel": {"id": created}, "queue.retry": {"id": created},
            "queue.prioritize": {"id": created, "priority": 3.0}, "queue.add": dict(SPEC, idempotency_key="m-2")}
    try:
        for op in protocol.ADMIN_OPS:
            before = version()
            call(op, args.get(op), queue=queue, catalog=catalog, registry=registry, workers=lambda: ["w1"])
            assert (version() != before) == (op in admin.WRITE_OPS), op
    finally:
        watcher.close()


def test_a_queue_operation_the_storage_failed_is_never_bad_field() -> None:
    """bad_field makes a worker fail its request and drop its episode: only for a refusal of the request itself.
    The storage failing under it is unavailable (it passes) or internal (it does not), and the worker asks again."""
    def raised_from(cause: BaseException, error: type[StorageError]) -> StorageError:
        try:
            try:
                raise cause
            except BaseException as exc:
                raise error(f"cannot renew: {exc}") from exc
        except StorageError as exc:
            return exc

    try:
        sqlite3.connect(":memory:").execute("select * from no_such_table")
    except sqlite3.Error as exc:
        damaged = exc
    assert admin.protocol_error(raised_from(damaged, QueueError)).code == ErrorCode.INTERNAL
    not_a_dir = OSError(errno.ENOTDIR, "Not a directory")
    assert admin.protocol_error(raised_from(not_a_dir, QueueError)).code == ErrorCode.INTERNAL
    assert admin.protocol_error(raised_from(damaged, QueueUnavailableError)).code == ErrorCode.UNAVAILABLE
    assert admin.protocol_error(QueueError("priority: expected a number")).code == ErrorCode.BAD_FIELD
