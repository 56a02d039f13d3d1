"""Admin replies and wire refusals end to end: a real service, a real Zenoh client on loopback, the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from orchestrator import protocol, transport
from orchestrator.cli import main
from orchestrator.messages import AdminRequest
from orchestrator.protocol import Keys
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage.requests import NewRequest

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}


@pytest.fixture
def service(data_dir: Path, endpoint: str, namespace: str):
    svc = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,)))
    svc.start()
    yield svc
    svc.stop()


def _answer(client, key: str, payload: bytes) -> dict:
    """The reply to ``payload`` on ``key`` as JSON (error replies included)."""
    return json.loads(transport.query(client, key, payload, timeout=10))


@pytest.mark.parametrize("where, payload", [
    ("lease", b'{"v": 1, "worker_id": ' + b"[" * 5000 + b"]" * 5000 + b"}"),
    ("stats", b'{"v": 1, "op": "stats", "args": {"a": ' + b"[" * 990 + b"]" * 990 + b"}}"),
    ("queue.add", b'{"v": 1, "op": "queue.add", "args": {"task": "push", "shape": "box", "start_state": '
                  + json.dumps(START).encode() + b', "policy_params": {"a": ' + b"[" * 990 + b"]" * 990 + b"}}}"),
])
def test_deeply_nested_json_is_bad_json_not_internal(service, client, namespace, where, payload) -> None:
    keys = Keys(namespace)
    assert len(payload) < protocol.MAX_MESSAGE_BYTES
    answer = _answer(client, keys.lease if where == "lease" else keys.admin(where), payload)
    assert (answer["ok"], answer["error"]) == (False, "bad_json"), answer


@pytest.mark.parametrize("status", [[], "bogus"])
def test_models_ls_bad_status_is_bad_field(service, client, namespace, status) -> None:
    payload = AdminRequest(op="models.ls", args={"status": status}).to_json()
    answer = _answer(client, Keys(namespace).admin("models.ls"), payload)
    assert (answer["ok"], answer["error"]) == (False, "bad_field"), answer
    assert "candidate, champion, retired, rejected" in answer["message"]


def test_queue_ls_of_large_requests_fits_and_the_cli_says_it_was_cut(service, client, endpoint, namespace,
                                                                    capsys) -> None:
    for _ in range(20):  # each 15 KB of reason: 300 KB in all, past MAX_MESSAGE_BYTES
        service.queue.enqueue(NewRequest(task="push", shape="box", start_state=START,
                                         reason={"note": "x" * 15_000}))
    reply = transport.query(client, Keys(namespace).admin("queue.ls"), b"", timeout=10)
    body = protocol.parse_reply(reply)  # refused as too_large before
    assert body["truncated"] is True and body["total"] == 20 and 0 < len(body["requests"]) < 20

    argv = ["queue", "ls", "--connect", endpoint, "--namespace", namespace, "--timeout", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"list cut at {len(body['requests'])} of 20 requests" in out and "--status" in out
    assert main([*argv, "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert listed["truncated"] is True and listed["total"] == 20
    assert main([*argv, "--limit", "2"]) == 0
    assert "2 of 20 requests (--limit N shows up to 200)" in capsys.readouterr().out
