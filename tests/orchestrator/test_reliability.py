"""Reliability with real processes: a service and workers as subprocesses, killed and paused.

Small episodes (16x16 frames, 10-30 steps) and short leases. ``--realtime 1`` paces a
worker's episode to steps / 10 Hz seconds, which is how a test catches it mid-episode.
"""

from __future__ import annotations

import signal
import sqlite3
from pathlib import Path
from typing import Any

import pytest
from orchestrator import messages, protocol, transport
from orchestrator.messages import LeaseGrant
from orchestrator.protocol import ErrorCode, Keys, ProtocolError
from storage.catalog import Catalog
from storage.episodes import encode_episode
from storage.queue import RequestQueue
from storage.requests import NewRequest, Request, RequestStatus
from tests.conftest import wait_for
from workers.collect import collect_episode

pytestmark = pytest.mark.slow

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}


class Ops:
    """The test's own view: a Zenoh client (as the CLI would use) and the service's SQLite files."""

    def __init__(self, endpoint: str, namespace: str, data_dir: Path) -> None:
        self.keys = Keys(namespace)
        self.data_dir = data_dir
        self.session = transport.open_session(connect=[endpoint])
        self._queue: RequestQueue | None = None

    def close(self) -> None:
        if self._queue is not None:
            self._queue.close()
        self.session.close()

    def call(self, key: str, payload: bytes = b"", attachment: bytes | None = None, timeout: float = 10) -> dict:
        return protocol.parse_reply(transport.query(self.session, key, payload, attachment, timeout=timeout))

    def admin(self, op: str, timeout: float = 10, **args: Any) -> dict:
        return self.call(self.keys.admin(op), messages.AdminRequest(op=op, args=args).to_json(), timeout=timeout)

    def wait_up(self) -> None:
        self.admin("stats", timeout=90)  # the service process imports torch on the way up

    def add(self, steps: int = 10, **kw: Any) -> str:
        body = self.admin("queue.add", task="push", shape="box", start_state=START, steps=steps, **kw)
        return body["request"]["id"]

    @property
    def queue(self) -> RequestQueue:
        if self._queue is None:
            self._queue = RequestQueue(Catalog(self.data_dir).db_path)
        return self._queue

    def get(self, request_id: str) -> Request:
        return self.queue.get(request_id)

    def episodes(self) -> list:
        return Catalog(self.data_dir).list()

    def mcap_files(self) -> set[Path]:
        return {p.resolve() for p in (self.data_dir / "episodes").rglob("*.mcap")}


@pytest.fixture
def ops(endpoint: str, namespace: str, data_dir: Path):
    o = Ops(endpoint, namespace, data_dir)
    yield o
    o.close()


def leased_by(ops: Ops, request_id: str, worker: str) -> bool:
    r = ops.get(request_id)
    return r.status == RequestStatus.LEASED and r.worker_id == worker


def assert_stored_once(ops: Ops, request_id: str, worker: str) -> None:
    r = ops.get(request_id)
    assert (r.status, r.worker_id) == (RequestStatus.DONE, worker), r
    rows = [e for e in ops.episodes() if e.request_id == request_id]
    assert [e.episode_id for e in rows] == [r.episode_id]
    assert {e.path.resolve() for e in ops.episodes()} == ops.mcap_files(), "every file on disk is indexed, no other"


def test_sigkilled_worker_lease_is_released_by_liveliness_and_done_once(spawn_service, spawn_worker, ops) -> None:
    service = spawn_service("--lease-s", "30")  # only the liveliness loss can free it in time
    ops.wait_up()
    rid = ops.add(steps=40)
    a = spawn_worker("A", "--realtime", "1")
    wait_for(lambda: leased_by(ops, rid, "A"), timeout=30, message="A leases the request")
    a.signal(signal.SIGKILL)
    wait_for(lambda: ops.get(rid).status == RequestStatus.QUEUED, timeout=15,
             message="A's lease released through liveliness, well before the 30 s lease")
    assert "worker A lost" in ops.get(rid).last_error
    b = spawn_worker("B", "--once")
    assert b.wait(60) == 0
    assert_stored_once(ops, rid, "B")
    assert ops.get(rid).attempts == 1
    assert service.alive()


def test_paused_worker_is_fenced_off_and_the_request_done_once(spawn_service, spawn_worker, ops) -> None:
    spawn_service("--lease-s", "1.5")
    ops.wait_up()
    rid = ops.add(steps=20)
    a = spawn_worker("A", "--realtime", "1")
    wait_for(lambda: leased_by(ops, rid, "A"), timeout=30, message="A leases the request")
    a.signal(signal.SIGSTOP)
    wait_for(lambda: ops.get(rid).status == RequestStatus.QUEUED, timeout=15, message="A's lease expires")
    b = spawn_worker("B", "--once")
    assert b.wait(60) == 0
    assert_stored_once(ops, rid, "B")
    a.signal(signal.SIGCONT)
    # A wakes up holding token 1 of a request now done with token 2: its renew or its upload,
    # whichever goes first, is refused by the fencing token, and it drops the episode.
    wait_for(lambda: "no longer ours" in a.log(), timeout=30, message="A is refused by the fence")
    assert "stale_token" in a.log()
    assert_stored_once(ops, rid, "B")
    assert ops.get(rid).token == 2 and a.alive()


def test_sigkilled_orchestrator_restarts_with_every_acknowledged_request(spawn_service, spawn_worker, ops,
                                                                         data_dir: Path) -> None:
    first = spawn_service("--lease-s", "5")
    ops.wait_up()
    acknowledged = [ops.add(steps=10) for _ in range(6)]
    spawn_worker("W", "--realtime", "1")
    wait_for(lambda: ops.queue.counts()["done"] >= 1, timeout=60, message="some work done before the crash")
    first.signal(signal.SIGKILL)
    first.wait(10)
    with pytest.raises(transport.NoReplyError):
        ops.admin("stats", timeout=0.5)
    spawn_service("--lease-s", "5", name="service-restarted")
    ops.wait_up()
    wait_for(lambda: any(w["id"] == "W" and w["alive"] for w in ops.admin("workers.ls")["workers"]),
             timeout=30, message="the restarted service sees the worker's liveliness token again")
    acknowledged.append(ops.add(steps=10))
    wait_for(lambda: all(ops.get(r).status == RequestStatus.DONE for r in acknowledged), timeout=90,
             message="every acknowledged request done after the restart")
    episodes = ops.episodes()
    assert sorted(e.request_id for e in episodes) == sorted(acknowledged), "each request stored exactly once"
    assert {ops.get(r).episode_id for r in acknowledged} == {e.episode_id for e in episodes}
    assert {e.path.resolve() for e in episodes} == ops.mcap_files()
    with sqlite3.connect(data_dir / "catalog.sqlite") as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone() == ("ok",)


def _lease(ops: Ops, worker: str) -> LeaseGrant:
    return LeaseGrant.from_dict(ops.call(ops.keys.lease, messages.LeaseRequest(worker_id=worker).to_json())["grant"])


def _episode(grant: LeaseGrant, worker: str) -> bytes:
    return encode_episode(collect_episode(start_state=grant.start_state, policy=grant.policy, seed=grant.seed,
                                          steps=grant.steps, image_size=16, request_id=grant.request_id,
                                          worker_id=worker))


def _send(ops: Ops, kind: str, grant: LeaseGrant, worker: str, data: bytes = b"") -> str:
    """Send one worker message; 'ok', 'duplicate' or the refusal's error code."""
    if kind == "renew":
        key, payload, att = ops.keys.renew, messages.RenewRequest(
            request_id=grant.request_id, token=grant.token, worker_id=worker).to_json(), None
    elif kind == "fail":
        key, payload, att = ops.keys.fail, messages.FailRequest(
            request_id=grant.request_id, token=grant.token, worker_id=worker, error="late").to_json(), None
    else:
        key, payload = ops.keys.upload, data
        att = messages.UploadHeader.for_payload(data, request_id=grant.request_id, token=grant.token,
                                                worker_id=worker).to_json()
    try:
        body = ops.call(key, payload, att)
    except ProtocolError as exc:
        return exc.code.value
    return "duplicate" if body.get("duplicate") else "ok"


def _end_state(ops: Ops, rid: str) -> tuple:
    r = ops.get(rid)
    return r.status, r.attempts, r.token, len([e for e in ops.episodes() if e.request_id == rid])


def test_duplicate_and_out_of_order_messages_leave_the_same_end_state(spawn_service, ops) -> None:
    spawn_service("--lease-s", "30")
    ops.wait_up()
    clean, messy = ops.add(priority=2.0), ops.add(priority=1.0)
    g = _lease(ops, "w1")
    assert g.request_id == clean
    assert [_send(ops, "renew", g, "w1"), _send(ops, "upload", g, "w1", _episode(g, "w1"))] == ["ok", "ok"]

    m = _lease(ops, "w1")
    assert m.request_id == messy
    data = _episode(m, "w1")
    future = LeaseGrant.from_dict({**m.to_dict(), "token": m.token + 1})
    early = [_send(ops, "upload", future, "w1", data),  # a token from the future
             _send(ops, "renew", m, "w2"),  # the right token from the wrong worker
             _send(ops, "fail", future, "w1")]
    assert early == ["stale_token"] * 3
    late = [_send(ops, "upload", m, "w1", data), _send(ops, "upload", m, "w1", data),  # duplicated
            _send(ops, "renew", m, "w1"), _send(ops, "fail", m, "w1"),  # after completion
            _send(ops, "upload", m, "w1", data)]
    assert late == ["ok", "duplicate", "stale_token", "stale_token", "duplicate"]
    assert _end_state(ops, clean) == _end_state(ops, messy) == (RequestStatus.DONE, 0, 1, 1)


def test_malformed_messages_on_every_key_get_errors_and_the_service_stays_up(spawn_service, ops) -> None:
    service = spawn_service()
    ops.wait_up()
    rid = ops.add()
    big = b'{"v": 1, "worker_id": "' + b"x" * (protocol.MAX_MESSAGE_BYTES + 1) + b'"}'
    bad = [b"", b"\xff\xfe", b"{", b"[]", b'{"v": 99, "worker_id": "w"}', b'{"worker_id": "w"}',
           b'{"v": 1, "worker_id": 7}', b'{"v": 1, "request_id": "../../etc", "token": -1, "worker_id": "w"}', big]
    keys = [ops.keys.lease, ops.keys.renew, ops.keys.fail, ops.keys.release, ops.keys.upload] + \
        [ops.keys.admin(op) for op in protocol.ADMIN_OPS]
    codes = set()
    for key in keys:
        for payload in bad:
            if key == ops.keys.upload:  # the JSON header is the attachment; the payload is MCAP bytes
                reply = transport.query(ops.session, key, b"\x89MCAP0\r\n", payload or None, timeout=10)
            else:
                reply = transport.query(ops.session, key, payload, timeout=10)
            if key.startswith(f"{ops.keys.namespace}/admin/") and payload == b"":
                continue  # "no arguments": a valid query for the list ops
            with pytest.raises(ProtocolError) as info:
                protocol.parse_reply(reply)
            codes.add(info.value.code)
    assert codes <= {ErrorCode.BAD_JSON, ErrorCode.BAD_VERSION, ErrorCode.BAD_FIELD, ErrorCode.TOO_LARGE}
    assert ErrorCode.TOO_LARGE in codes and ErrorCode.BAD_VERSION in codes
    assert service.alive()
    assert ops.get(rid).status == RequestStatus.QUEUED and ops.queue.counts()["queued"] == 1
    assert ops.episodes() == [] and ops.mcap_files() == set()
    assert _lease(ops, "w1").request_id == rid


def test_poison_request_ends_dead_after_max_attempts_and_never_loops(spawn_service, spawn_worker, ops) -> None:
    spawn_service("--lease-s", "5")
    ops.wait_up()
    with pytest.raises(ProtocolError) as refused:  # queue.add refuses what no worker can do ...
        ops.add(policy_params={"fail": True})
    assert refused.value.code == ErrorCode.BAD_FIELD and "unknown parameter" in refused.value.message
    # ... so it goes straight into the queue file, as a request of an older version would be there
    poison = ops.queue.enqueue(NewRequest(task="push", shape="box", start_state=START, policy="push",
                                          policy_params={"fail": True}, steps=10, max_attempts=3, priority=5.0))[0].id
    w = spawn_worker("W")
    wait_for(lambda: ops.get(poison).status == RequestStatus.DEAD, timeout=60, message="the poison request dies")
    r = ops.get(poison)
    assert r.attempts == 3 and "unknown parameter" in r.last_error and "fail" in r.last_error
    good = ops.add()
    wait_for(lambda: ops.get(good).status == RequestStatus.DONE, timeout=60,
             message="the same worker goes on with good work")
    assert ops.get(poison).status == RequestStatus.DEAD and ops.get(poison).attempts == 3
    assert w.log().count("collection of " + poison) == 3
