"""orchestrator.service in-process, driven by a real Zenoh client session over loopback."""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from orchestrator import messages, protocol, transport
from orchestrator.messages import LeaseGrant
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from orchestrator.protocol import ErrorCode, ProtocolError
from orchestrator.serviceconfig import ServiceConfig, ServiceError
from orchestrator.uploads import StoredEpisode
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.episodes import encode_episode
from storage.queue import RequestQueue
from storage.errors import QueueUnavailableError
from storage.requests import NewRequest, RequestStatus
from tests.conftest import wait_for
from workers.collect import collect_episode

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}


DEFAULT_PHYSICS = {k: default for k, (_, _, default) in protocol.PHYSICS_RANGES.items()}


def new_request(shape: str = "box", **kw: Any) -> NewRequest:
    return NewRequest(task="push", shape=shape, start_state={**START, "shape": shape}, policy="push",
                      steps=kw.pop("steps", 5), **kw)


def call(client: zenoh.Session, key: str, payload: bytes = b"", attachment: bytes | None = None) -> dict:
    return protocol.parse_reply(transport.query(client, key, payload, attachment, timeout=10))


def lease(client, keys, worker: str = "w1", **kw) -> LeaseGrant:
    body = call(client, keys.lease, messages.LeaseRequest(worker_id=worker, **kw).to_json())
    return LeaseGrant.from_dict(body["grant"])


def episode_bytes(grant: LeaseGrant, worker: str = "w1", size: int = 16, **meta: Any) -> bytes:
    """What a worker collects for ``grant``; ``meta``: metadata fields it then claims instead."""
    ep = collect_episode(start_state=grant.start_state, policy=grant.policy, policy_params=grant.policy_params,
                         seed=grant.seed, steps=grant.steps, image_size=size, request_id=grant.request_id,
                         worker_id=worker)
    ep.meta = dataclasses.replace(ep.meta, **meta)
    return encode_episode(ep)


def upload(client, keys, grant: LeaseGrant, data: bytes, worker: str = "w1", **header_kw: Any) -> dict:
    header = messages.UploadHeader.for_payload(data, request_id=grant.request_id, token=grant.token,
                                               worker_id=worker)
    raw = {**header.to_dict(), **header_kw}
    return call(client, keys.upload, data, protocol.encode({"v": 1, **raw}))


def refused(code: ErrorCode, fn, *args, **kw) -> str:
    with pytest.raises(ProtocolError) as info:
        fn(*args, **kw)
    assert info.value.code == code, info.value
    return info.value.message


def test_config_is_validated(data_dir: Path) -> None:
    with pytest.raises(ServiceError, match="lease_s"):
        ServiceConfig(data_dir=data_dir, lease_s=0)
    with pytest.raises(ServiceError, match="namespace"):
        ServiceConfig(data_dir=data_dir, namespace="a/*")
    with pytest.raises(ServiceError, match="mode"):
        ServiceConfig(data_dir=data_dir, mode="router")


def test_lease_grants_the_best_matching_request_or_says_no_work(service, client, keys) -> None:
    refused(ErrorCode.NO_WORK, lease, client, keys)
    low, _ = service.queue.enqueue(new_request("box", priority=1.0))
    high, _ = service.queue.enqueue(new_request("T", priority=5.0))
    grant = lease(client, keys, shapes=["box"])
    assert (grant.request_id, grant.token, grant.shape) == (low.id, 1, "box")
    assert grant.seed == messages.request_seed(low.id, 1) and grant.lease_s == 30.0
    assert lease(client, keys, worker="w2").request_id == high.id
    refused(ErrorCode.NO_WORK, lease, client, keys, worker="w3")
    again = lease(client, keys)  # a worker holds one lease at a time: asking again answers it again
    assert (again.request_id, again.token, again.seed) == (low.id, 1, grant.seed)
    r = service.queue.get(low.id)
    assert (r.status, r.worker_id) == (RequestStatus.LEASED, "w1")


def test_a_refusal_is_logged_on_one_line_whatever_the_peer_sent(service, client, keys, caplog) -> None:
    forged = "x\n2026-11-21 00:00:00,000 orchestrator.service ERROR forged line"
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        refused(ErrorCode.BAD_FIELD, call, client, keys.lease, protocol.encode({"v": 1, "worker_id": "w1", forged: 1}))
        wait_for(lambda: any("refused" in r.getMessage() for r in caplog.records), message="the refusal's log line")
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert lines and all("\n" not in line for line in lines) and "'x\\n2026" in lines[0], lines


def test_renew_extends_a_live_lease_and_refuses_a_stale_one(make_service, client, keys) -> None:
    service = make_service(lease_s=2.0)
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    msg = messages.RenewRequest(request_id=grant.request_id, token=grant.token, worker_id="w1").to_json()
    assert call(client, keys.renew, msg)["expires_at"] >= grant.expires_at
    wrong = messages.RenewRequest(request_id=grant.request_id, token=grant.token, worker_id="w2").to_json()
    refused(ErrorCode.STALE_TOKEN, call, client, keys.renew, wrong)
    unknown = messages.RenewRequest(request_id="nope", token=1, worker_id="w1").to_json()
    refused(ErrorCode.UNKNOWN_REQUEST, call, client, keys.renew, unknown)


def test_fail_counts_attempts_until_dead(service, client, keys) -> None:
    request, _ = service.queue.enqueue(new_request(max_attempts=2))
    statuses = []
    for _ in range(2):
        grant = lease(client, keys)
        body = call(client, keys.fail, messages.FailRequest(request_id=grant.request_id, token=grant.token,
                                                            worker_id="w1", error="sim exploded").to_json())
        statuses.append((body["status"], body["attempts"]))
    assert statuses == [("queued", 1), ("dead", 2)]
    assert service.queue.get(request.id).last_error == "sim exploded"
    refused(ErrorCode.NO_WORK, lease, client, keys)


def test_release_gives_a_lease_back_without_an_attempt(service, client, keys) -> None:
    events: list[dict] = []
    sub = client.declare_subscriber(keys.events_all, lambda s: events.append(json.loads(s.payload.to_bytes())))

    def subscribed() -> bool:  # the subscription reaches the service asynchronously: probe until it has
        service.publish(protocol.EventKind.WORKER_JOINED, {"worker_id": "probe"})
        return bool(events)

    wait_for(subscribed, message="the event subscription is in place")
    request, _ = service.queue.enqueue(new_request(max_attempts=1))
    grant = lease(client, keys)
    msg = messages.ReleaseRequest(request_id=grant.request_id, token=grant.token, worker_id="w1").to_json()
    assert call(client, keys.release, msg) == {"status": "queued", "attempts": 0}
    wait_for(lambda: [e["data"] for e in events if e["kind"] == "request.released"] == [
        {"request_id": request.id, "worker_id": "w1", "token": 1, "status": "queued", "attempts": 0}],
        message="one request.released event")
    sub.undeclare()
    refused(ErrorCode.STALE_TOKEN, call, client, keys.release, msg)  # not ours any more
    after = service.queue.get(request.id)
    assert (after.status, after.attempts, after.last_error) == (RequestStatus.QUEUED, 0, None)
    again = lease(client, keys, worker="w2")  # max_attempts=1 and still alive: nothing was counted
    assert (again.request_id, again.token) == (request.id, 2)
    wrong = messages.ReleaseRequest(request_id=again.request_id, token=again.token, worker_id="w1").to_json()
    refused(ErrorCode.STALE_TOKEN, call, client, keys.release, wrong)
    unknown = messages.ReleaseRequest(request_id="nope", token=1, worker_id="w1").to_json()
    refused(ErrorCode.UNKNOWN_REQUEST, call, client, keys.release, unknown)


def test_expired_leases_are_reaped(make_service, client, keys) -> None:
    service = make_service(lease_s=0.3)
    request, _ = service.queue.enqueue(new_request())
    lease(client, keys)
    wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
             message="the expired lease goes back to the queue")
    assert service.queue.get(request.id).attempts == 1
    assert lease(client, keys, worker="w2").token == 2


def test_lease_expiry_outlives_an_unexpected_failure_in_maintenance(make_service, client, keys) -> None:
    service = make_service(lease_s=0.3)
    real, failed = service.catalog.count, []

    def count_once_failing(*args, **kw):  # one failure of a kind nobody planned for
        if not failed:
            failed.append(1)
            raise RuntimeError("something unexpected")
        return real(*args, **kw)

    service.catalog.count = count_once_failing
    wait_for(lambda: failed, message="the maintenance task to fail once")
    request, _ = service.queue.enqueue(new_request())
    lease(client, keys)
    wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
             message="leases still expire after the failure")


def test_the_champion_gauges_follow_the_registry_whoever_promotes(service, data_dir) -> None:
    """A champion promoted by another process (train, models promote) shows in /metrics."""
    assert "activecollect_champion_h1_mse NaN" in service.metrics.render()
    registry = ModelRegistry(data_dir)
    version = registry.register(b"weights", {}, {"h1_mse": 0.004}, "snap", "evalhash")
    registry.promote(version)
    wait_for(lambda: "activecollect_champion_h1_mse 0.004" in service.metrics.render(),
             message="the maintenance task to read the new champion")
    assert f'activecollect_champion_info{{version="{version}"}} 1.0' in service.metrics.render()


def test_lost_worker_releases_its_leases_at_once(service, client, keys, endpoint) -> None:
    request, _ = service.queue.enqueue(new_request())
    worker = transport.open_session(connect=[endpoint])
    token = worker.liveliness().declare_token(keys.worker("w9"))
    wait_for(lambda: "w9" in service.workers(), message="the service sees the worker")
    grant = lease(worker, keys, worker="w9")
    assert grant.request_id == request.id
    token.undeclare()
    worker.close()
    wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
             message="the lost worker's lease is released (lease_s is 30 s)")
    assert "w9" not in service.workers()
    assert "worker w9 lost" in service.queue.get(request.id).last_error


BAD_MESSAGES = {
    "bad_json": b"{not json",
    "bad_version": b'{"v": 2, "worker_id": "w1"}',
    "no_version": b'{"worker_id": "w1"}',
    "bad_field": b'{"v": 1, "worker_id": "w 1/*"}',
    "unknown_field": b'{"v": 1, "worker_id": "w1", "extra": 1}',
    "too_large": b'{"v": 1, "worker_id": "' + b"x" * (protocol.MAX_MESSAGE_BYTES + 10) + b'"}',
    "empty": b"",
    "array": b"[1, 2]",
}


@pytest.mark.parametrize("which", ["lease", "renew", "fail", "upload", "admin"])
def test_malformed_messages_get_error_replies_and_change_nothing(service, client, keys, data_dir, which) -> None:
    request, _ = service.queue.enqueue(new_request())
    before = service.queue.get(request.id)
    key = keys.admin("queue.add") if which == "admin" else getattr(keys, which)
    for name, payload in BAD_MESSAGES.items():
        if which == "upload":  # the header travels as the attachment
            reply = transport.query(client, key, b"\x89MCAP0\r\n", payload, timeout=10)
        else:
            reply = transport.query(client, key, payload, timeout=10)
        if which == "admin" and name == "empty":
            continue  # an empty admin payload means "the key's op with no arguments" (refused below anyway)
        with pytest.raises(ProtocolError) as info:
            protocol.parse_reply(reply)
        expected = {"bad_json", "bad_version", "bad_field", "too_large", "unknown_op"}
        assert info.value.code.value in expected, (name, info.value)
    assert service.queue.get(request.id) == before
    assert service.queue.counts()["queued"] == 1 and Catalog(data_dir).count() == 0
    assert lease(client, keys).request_id == request.id  # still serving


def test_admin_ops_and_events(service, client, keys, namespace) -> None:
    events: list[dict] = []
    sub = client.declare_subscriber(keys.events_all, lambda s: events.append(json.loads(s.payload.to_bytes())))
    spec = {"task": "push", "shape": "T", "start_state": {**START, "shape": "T"}, "idempotency_key": "k1"}
    added = call(client, keys.admin("queue.add"), messages.AdminRequest(op="queue.add", args=spec).to_json())
    again = call(client, keys.admin("queue.add"), messages.AdminRequest(op="queue.add", args=spec).to_json())
    assert added["created"] and not again["created"] and added["request"]["id"] == again["request"]["id"]
    rid = added["request"]["id"]
    listed = call(client, keys.admin("queue.ls"))  # empty payload: the key's op, no arguments
    assert [r["id"] for r in listed["requests"]] == [rid] and listed["counts"]["queued"] == 1

    def op(name: str, **args: Any) -> dict:
        return call(client, keys.admin(name), messages.AdminRequest(op=name, args=args).to_json())

    assert op("queue.prioritize", id=rid, priority=7.5)["request"]["priority"] == 7.5
    assert op("queue.cancel", id=rid)["request"]["status"] == "cancelled"
    assert op("queue.retry", id=rid)["request"]["status"] == "queued"
    assert op("queue.show", id=rid)["request"]["start_state"]["shape"] == "T"
    refused(ErrorCode.UNKNOWN_REQUEST, op, "queue.show", id="nope")
    # an operator's typo, not a worker's refusal: an alert on source="worker" does not fire on it
    counted = lambda source: service.metrics.registry.get_sample_value(  # noqa: E731
        "activecollect_refusals_total", {"reason": "unknown_request", "source": source})
    assert (counted("operator"), counted("worker")) == (1, None)
    assert op("stats")["requests"]["queued"] == 1
    assert op("workers.ls") == {"workers": [], "truncated": False, "total": 0}
    wait_for(lambda: {e["kind"] for e in events} >= {"request.queued", "request.prioritized",
                                                      "request.cancelled", "request.retried"},
             message="admin events")
    sub.undeclare()
    with pytest.raises(transport.RemoteError):  # a pattern has no concrete key to answer on
        transport.query(client, f"{namespace}/admin/*", timeout=5)


def test_planner_and_callbacks_run_off_the_query_path(make_service, client, keys) -> None:
    gate = threading.Event()
    seen: list[StoredEpisode] = []

    class OnePerEpisode:
        name = "test"

        def seed(self, n: int) -> list[NewRequest]:
            return [new_request("disk") for _ in range(n)]

        def plan(self, episodes) -> list[NewRequest]:
            gate.wait(30)  # a slow scorer: leasing must not wait for it
            return [new_request("L") for _ in episodes]

    service = make_service(planner=lambda ctx: OnePerEpisode(), seed_requests=2, on_episode=(seen.append,))
    assert service.queue.counts()["queued"] == 2
    grant = lease(client, keys)
    upload(client, keys, grant, episode_bytes(grant))
    second = lease(client, keys)  # answered while the planner is still blocked
    assert second.shape == "disk"
    assert service.heap.trims == 0  # the heap's free memory is given back after a batch (what scoring freed)
    gate.set()
    wait_for(lambda: len(seen) == 1, message="the on_episode callback ran")
    assert seen[0].request_id == grant.request_id and seen[0].episode.frames.shape[1:] == (16, 16, 3)
    wait_for(lambda: service.heap.trims == 1 or not service.heap.available, message="the heap trimmed")
    wait_for(lambda: service.queue.counts()["queued"] == 1, message="the planner's request is queued")
    assert lease(client, keys, worker="w2").shape == "L"  # (w1 still holds the second)


def test_the_queue_is_topped_up_when_the_planner_asks_for_nothing(make_service, client, keys) -> None:
    # A real planner that plans nothing from new episodes (as an active planner does when no state
    # passes its threshold): without the floor the queue runs dry and collection stops for good.
    planner = lambda ctx: UniformPlanner(UniformPlannerConfig(per_episode=0, steps=5), np.random.default_rng(0))
    service = make_service(planner=planner, min_queued=2)
    wait_for(lambda: service.queue.counts()["queued"] == 2, message="the floor reached")
    for _ in range(3):
        grant = lease(client, keys)
        upload(client, keys, grant, episode_bytes(grant))
        wait_for(lambda: service.queue.counts()["queued"] == 2, message="topped up again")
    counts = service.queue.counts()
    assert counts["done"] == 3 and counts["queued"] == 2 and counts["leased"] == 0
    reasons = {r.reason["planner"] for r in service.queue.list(status="queued")}
    assert reasons == {"top-up"}  # the planner's uniform seed draws, named for why they exist


def test_min_queued_is_validated(data_dir) -> None:
    for bad in (-1, 2.5, True):
        with pytest.raises(ServiceError, match="min_queued"):
            ServiceConfig(data_dir=data_dir, min_queued=bad)


def test_restart_keeps_everything_acknowledged(make_service, client, keys, data_dir) -> None:
    service = make_service()
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    upload(client, keys, grant, episode_bytes(grant))
    service.stop()
    service = make_service()
    assert service.queue.get(grant.request_id).status == RequestStatus.DONE
    assert Catalog(data_dir).count() == 1
    q = RequestQueue(Catalog(data_dir).db_path)
    assert q.counts()["done"] == 1
    q.close()


def test_after_a_storage_outage_live_leases_get_a_full_term_before_any_expires(make_service) -> None:
    """While the disk was full no worker could renew: when writes work again, leases are extended first
    (a worker retrying its upload would otherwise find its lease expired and lose the episode)."""
    service = make_service(lease_s=30.0)
    request, _ = service.queue.enqueue(new_request())
    with service._writes:  # the reaper waits while the outage is set up
        lease = service.queue.lease("w1", lease_s=1.0, now=time.time() - 10)  # ran out during the outage
        service.storage.write_failed(QueueUnavailableError("queue transaction failed: database or disk is full"))
    wait_for(lambda: service.storage.down_since is None, message="the reaper to see the storage back")
    after = service.queue.get(request.id)
    assert (after.status, after.token, after.attempts) == (RequestStatus.LEASED, lease.token, 0)
    assert after.lease_expires > time.time() + 20


def test_leases_taken_before_a_restart_get_a_full_term_after_it(make_service, client, keys) -> None:
    """No worker can renew while the service is down: a lease that ran out meanwhile is not ended at start-up
    (an attempt counted, the worker's collected episode dropped); its worker renews and uploads."""
    service = make_service(lease_s=30.0)
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    service.stop()
    down = RequestQueue(Catalog(service.config.data_dir).db_path)
    down.renew(grant.request_id, grant.token, "w1", lease_s=1.0, now=time.time() - 60)  # ran out while down
    assert down.get(request.id).lease_expires < time.time()
    down.close()

    service = make_service(lease_s=30.0)

    after = service.queue.get(request.id)
    assert (after.status, after.token, after.attempts) == (RequestStatus.LEASED, grant.token, 0)
    assert time.time() + 20 < after.lease_expires <= time.time() + 30
    renew = messages.RenewRequest(request_id=grant.request_id, token=grant.token, worker_id="w1").to_json()
    assert call(client, keys.renew, renew)["expires_at"] > time.time() + 20  # (the query waits for the reconnect)
    assert upload(client, keys, grant, episode_bytes(grant))["request_id"] == request.id
    assert service.queue.get(request.id).status == RequestStatus.DONE


def test_a_start_moves_aside_the_checkpoint_folders_no_model_row_names(make_service, data_dir, caplog) -> None:
    """A retrain killed between renaming its checkpoint folder into place and committing the row leaves a folder
    nothing names; the start-up sweep moves it to models/.orphans/ (kept, not deleted) and leaves the models alone."""
    reg = ModelRegistry(data_dir)
    champion = reg.register(b"weights" * 10, {}, {"h1_mse": 0.1}, "snap", "split-aaaa")
    reg.gate(champion)
    stray = reg.models_dir / "m000007-0badf00d"
    stray.mkdir()
    (stray / "weights.pt").write_bytes(b"a killed register's")

    with caplog.at_level(logging.WARNING, logger="orchestrator.service"):
        make_service()

    assert not stray.exists()
    assert (data_dir / "models" / ".orphans" / "m000007-0badf00d" / "weights.pt").read_bytes() == b"a killed register's"
    assert "moved 1 checkpoint folder(s) no model row names" in caplog.text and "m000007-0badf00d" in caplog.text
    assert reg.champion() == champion and reg.load_weights(champion) == b"weights" * 10


@pytest.mark.parametrize("cause", ["a file where orphans/ goes", "no space left on the device"])
def test_a_start_that_cannot_move_strays_aside_leaves_them_and_serves(make_service, client, keys, data_dir,
                                                                      monkeypatch, caplog, cause) -> None:
    """The start-up sweep moves unindexed episode files to orphans/<day>/; when that folder cannot be made
    the strays stay where they are (no row indexes them) and the service starts all the same."""
    Catalog(data_dir)
    stray = data_dir / "episodes" / "2026-01-01" / "0123456789abcdef0123456789abcdef.mcap"
    stray.parent.mkdir(parents=True)
    stray.write_bytes(b"renamed into place, then a crash before the commit")
    if cause.startswith("a file"):
        (data_dir / "orphans").write_text("in the way")
    else:
        real_mkdir = Path.mkdir

        def full_disk(self: Path, *args: Any, **kw: Any) -> None:
            if "orphans" in self.parts:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
            real_mkdir(self, *args, **kw)

        monkeypatch.setattr(Path, "mkdir", full_disk)

    with caplog.at_level(logging.WARNING, logger="orchestrator.service"):
        service = make_service()
    monkeypatch.undo()

    assert stray.read_bytes() == b"renamed into place, then a crash before the commit"
    assert "cannot move the files crashed ingests left aside" in caplog.text and "orphans" in caplog.text
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    assert upload(client, keys, grant, episode_bytes(grant))["request_id"] == request.id
