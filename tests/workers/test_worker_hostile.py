"""``activecollect worker`` under hostile input: flags that contradict each other, and a service whose upload reply
cannot be read (garbled, another release's version, not an object). The reply is not a refusal of the episode: the
service may hold it or not, and a retry says which (``duplicate`` if it was stored). The old worker reported the
request failed (an attempt counted against a request that did nothing wrong) and dropped the episode it held."""

from __future__ import annotations

import json
import threading
import time
from typing import Any, Callable

import pytest

from orchestrator import protocol, serving, transport
from orchestrator.protocol import ErrorCode, Keys
from tests.orchestrator.test_service import START
from tests.workers.test_agent_cli import MODULE, _stops
from workers import cli as worker_cli

GRANT = {"request_id": "r-garbled", "task": "push", "shape": "box", "start_state": {**START, "shape": "box"},
         "policy": "push", "policy_params": {}, "action_prefix": [], "steps": 5, "model_version": "", "token": 7,
         "expires_at": time.time() + 30, "lease_s": 30.0}


def _ok(**body: Any) -> bytes:
    return protocol.encode({"v": protocol.PROTOCOL_VERSION, "ok": True, **body})


class UploadService:
    """Real Zenoh queryables on the test's endpoint: one grant, then ``no_work``; renewals and failure reports
    acknowledged (each report kept); the upload answered ``first`` once, then stored."""

    def __init__(self, endpoint: str, namespace: str, first: bytes) -> None:
        self.session = transport.open_session(listen=[endpoint])
        self.leases, self.uploads, self.fails = 0, [], []
        self._lock, self._first, keys = threading.Lock(), first, Keys(namespace)
        handlers: dict[str, Callable[[transport.Incoming], bytes]] = {
            keys.lease: self._lease, keys.upload: self._upload, keys.fail: self._fail,
            keys.renew: lambda msg: _ok(expires_at=time.time() + 30)}
        self._servers = [serving.Server(self.session, key, lambda msg, h=h: transport.Response(h(msg)))
                         for key, h in handlers.items()]

    def _lease(self, msg: transport.Incoming) -> bytes:
        with self._lock:
            self.leases += 1
            return _ok(grant=GRANT) if self.leases == 1 else protocol.error_reply(ErrorCode.NO_WORK, "no work")

    def _upload(self, msg: transport.Incoming) -> bytes:
        with self._lock:
            self.uploads.append(json.loads(msg.attachment))
            return self._first if len(self.uploads) == 1 else _ok(request_id=GRANT["request_id"], episode_id="e-1")

    def _fail(self, msg: transport.Incoming) -> bytes:
        self.fails.append(json.loads(msg.payload))
        return _ok(status="queued", attempts=1)

    def close(self) -> None:
        for server in self._servers:
            server.close()
        self.session.close()


@pytest.fixture
def upload_service(endpoint: str, namespace: str):
    made: list[UploadService] = []

    def make(first: bytes) -> UploadService:
        made.append(UploadService(endpoint, namespace, first))
        return made[-1]

    yield make
    for service in made:
        service.close()


@pytest.mark.parametrize("first, words", [
    (b"\xff\x00 not json", "bad_json"),
    (b"[1, 2]", "bad_json: expected a JSON object, found list"),
    (protocol.encode({"v": protocol.PROTOCOL_VERSION + 1, "ok": True}), "bad_version"),
    (protocol.encode({"v": protocol.PROTOCOL_VERSION, "stored": True}), 'expected "ok": true or false'),
], ids=["garbled", "a-list", "another-version", "no-ok"])
def test_an_upload_reply_that_cannot_be_read_is_sent_again_not_reported_failed(upload_service, spawn_worker,
                                                                               first, words) -> None:
    service = upload_service(first)
    w = spawn_worker("G", "--once", "--timeout", "5")
    assert w.wait(10) == 0, w.log()
    log = w.log()
    assert "Traceback" not in log and "refused" not in log, log
    assert service.fails == [], service.fails  # no attempt counted against the request
    assert len(service.uploads) == 2 and service.uploads[0] == service.uploads[1]  # the same bytes again
    warned = [line for line in log.splitlines() if "WARNING upload: " in line]
    assert len(warned) == 1 and "the reply could not be read" in warned[0] and words in warned[0], log
    assert "uploaded r-garbled: episode e-1" in log, log


@pytest.mark.parametrize("prog", ["activecollect worker", MODULE])
def test_once_with_more_than_one_episode_is_a_contradiction_exit_2(capsys, prog) -> None:
    """(The old worker took ``--once --max-episodes 5``, handled one request and exited 0: the 5 was dropped
    without a word.)"""
    rc, err = _stops(capsys, prog, "--once", "--max-episodes", "5")
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith(f"{prog}: error: --max-episodes: expected 1 with --once (it handles at most one request), "
                          "found 5"), err


def test_once_with_one_episode_is_no_contradiction() -> None:
    config = worker_cli.config_from_args(worker_cli.build_parser().parse_args(["--once", "--max-episodes", "1"]))
    assert config.once and config.max_episodes == 1
