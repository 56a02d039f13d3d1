"""A worker facing a service that sends what it should not: a lease reply without a grant, a grant that is not
an object, a grant no worker can do; and an episode too large to upload. Each gets a clear word (a warning, or a
``fail`` naming the reason), never a worker that crashes and is restarted into the same reply."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from orchestrator import protocol, serving, transport
from orchestrator.messages import FailRequest
from orchestrator.protocol import ErrorCode, Keys
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator import conftest as orchestrator_fixtures
from tests.orchestrator.test_service import START, new_request
from workers import agent
from workers.agent import Worker, WorkerConfig

make_service = orchestrator_fixtures.make_service  # its in-process service, for these tests too

GRANT = {"request_id": "r-hostile", "task": "push", "shape": "box", "start_state": {**START, "shape": "box"},
         "policy": "push", "policy_params": {}, "action_prefix": [], "steps": 5, "model_version": "", "token": 3,
         "expires_at": time.time() + 30, "lease_s": 30.0}


class FakeService:
    """Real Zenoh queryables on the test's endpoint: ``lease`` answers ``first`` once and ``no_work`` after;
    ``fail`` records each report and acknowledges it."""

    def __init__(self, endpoint: str, namespace: str, first: bytes) -> None:
        self.session = transport.open_session(listen=[endpoint])
        self.leases, self.fails = 0, []
        self._lock = threading.Lock()
        keys, self._first = Keys(namespace), first
        self._servers = [serving.Server(self.session, keys.lease, self._lease),
                         serving.Server(self.session, keys.fail, self._fail)]

    def _lease(self, msg: transport.Incoming) -> transport.Response:
        with self._lock:
            self.leases += 1
            first = self.leases == 1
        return transport.Response(self._first if first else protocol.error_reply(ErrorCode.NO_WORK, "no work"))

    def _fail(self, msg: transport.Incoming) -> transport.Response:
        self.fails.append(FailRequest.from_json(msg.payload))
        return transport.Response(protocol.ok_reply(status="queued", attempts=1))

    def close(self) -> None:
        for server in self._servers:
            server.close()
        self.session.close()


@pytest.fixture
def fake_service(endpoint: str, namespace: str):
    made: list[FakeService] = []

    def make(first: bytes) -> FakeService:
        made.append(FakeService(endpoint, namespace, first))
        return made[-1]

    yield make
    for service in made:
        service.close()


def _ok(**body: Any) -> bytes:
    return protocol.encode({"v": protocol.PROTOCOL_VERSION, "ok": True, **body})


@pytest.mark.parametrize("reply, words", [
    (_ok(), "lease reply is malformed: expected a grant object, found None"),
    (_ok(grant=[1, 2]), "lease reply is malformed: expected a grant object, found [1, 2]"),
    (_ok(grant="r-1"), "lease reply is malformed: expected a grant object, found 'r-1'"),
    (protocol.error_reply(ErrorCode.BAD_FIELD, "tasks: expected a list"), "was refused, or its reply could not be "
                                                                          "read: bad_field: tasks: expected a list"),
    (protocol.encode({"v": protocol.PROTOCOL_VERSION + 1, "ok": True}), "bad_version"),
], ids=["no-grant", "a-list", "a-string", "refused", "another-release"])
def test_a_lease_reply_without_a_grant_is_a_warning_and_once_exits_1(fake_service, spawn_worker, reply,
                                                                     words) -> None:
    """(The old worker died on it with a KeyError / AttributeError traceback: restarted, it asked again. Then it
    said 'no work' and exited 0 with --once: a script could not tell another release's service from an empty
    queue.)"""
    service = fake_service(reply)
    w = spawn_worker("X", "--once")
    assert w.wait(60) == 1, w.log()
    log = w.log()
    assert words in log and "Traceback" not in log and "no work" not in log, log
    assert "a service of another release than this worker's, or one in trouble" in log
    assert any(line.startswith("python -m workers.agent: ") and words in line for line in log.splitlines()), log
    assert service.leases >= 1 and service.fails == []  # no request named: no failure to report


@pytest.mark.parametrize("change, words", [
    ({"start_state": {**START, "shape": "box", "agent": [1e9, 100.0]}}, "start_state.agent"),
    ({"steps": 10**9}, "steps"),
    ({"policy": "teleport"}, "policy"),
    ({"surprise": 1}, "unknown field(s) 'surprise'"),
], ids=["agent-off-the-table", "absurd-steps", "unknown-policy", "unknown-field"])
def test_a_grant_no_worker_can_do_is_reported_failed_with_the_reason(fake_service, spawn_worker, change,
                                                                     words) -> None:
    service = fake_service(_ok(grant={**GRANT, **change}))
    w = spawn_worker("Y", "--once")
    assert w.wait(60) == 0, w.log()
    assert "Traceback" not in w.log(), w.log()
    (fail,) = service.fails
    assert (fail.request_id, fail.token, fail.worker_id) == ("r-hostile", 3, "Y")
    assert fail.error.startswith("malformed lease: ") and words in fail.error, fail.error


def test_an_episode_too_large_to_upload_is_reported_failed_not_a_crash(make_service, endpoint, namespace,
                                                                        monkeypatch) -> None:
    """An episode whose MCAP outgrows what an upload may carry (a 1024 px catalog and a long prefix do): the
    request is failed naming the size (an attempt: every worker would record the same), and the worker lives.
    (The old worker raised the header's ProtocolError out of ``run``.)"""
    service = make_service()
    request, _ = service.queue.enqueue(new_request())
    monkeypatch.setattr(agent, "encode_episode", lambda episode: bytes(protocol.MAX_UPLOAD_BYTES + 1))
    worker = Worker(WorkerConfig(worker_id="Z", namespace=namespace, connect=(endpoint,), image_size=16, once=True))
    assert worker.run() == 0
    failed = wait_for(lambda: (r := service.queue.get(request.id)).attempts == 1 and r, message="the failure")
    assert failed.status == RequestStatus.QUEUED and worker.failed == 1
    assert (f"episode: expected at most {protocol.MAX_UPLOAD_BYTES} bytes of MCAP (the most an upload carries), "
            f"found {protocol.MAX_UPLOAD_BYTES + 1}") in failed.last_error, failed.last_error
