"""The wire contract (orchestrator.protocol, orchestrator.messages): every message round-trips, every malformed
input is refused with the right code."""

from __future__ import annotations

import ast
import hashlib
import json
from pathlib import Path

import pytest

import orchestrator.messages as m
import orchestrator.protocol as p
from orchestrator.protocol import ErrorCode, ProtocolError

START = {"shape": "T", "agent": [100.0, 120.0], "agent_vel": [0.0, 0.0], "object": [256.0, 256.0, 0.5],
         "object_vel": [0.0, 0.0, 0.0], "physics": {"mass": 1.0, "friction": 0.6, "ground_friction": 1.0}}

GRANT = dict(request_id="r1", task="push", shape="T", start_state=START, policy="push",
             policy_params={"side": "left", "noise": 0.1}, action_prefix=[[10.0, 20.0], [11.0, 21.0]],
             steps=50, model_version="m3", token=2, expires_at=1700000000.5, lease_s=30.0, seed=7)

MESSAGES = [
    m.LeaseRequest(worker_id="w-1", tasks=["push"], shapes=["T", "disk"]),
    m.LeaseRequest(worker_id="w.2"),
    m.LeaseGrant(**GRANT),
    m.RenewRequest(request_id="r1", token=2, worker_id="w-1"),
    m.UploadHeader.for_payload(b"mcap bytes", request_id="r1", token=2, worker_id="w-1"),
    m.FailRequest(request_id="r1", token=2, worker_id="w-1", error="pymunk exploded"),
    m.ReleaseRequest(request_id="r1", token=2, worker_id="w-1"),
    m.RequestSpec(task="push", shape="T", start_state=START, priority=2.5, idempotency_key="k",
                  reason={"model_version": "m3", "score": 0.9, "source_episode": "e", "step": 4}),
    m.AdminRequest(op="queue.ls", args={"status": "queued", "limit": 10}),
    m.Event(kind="request.done", at=1.0, data={"request_id": "r1"}),
]


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda msg: type(msg).__name__)
def test_round_trip(msg) -> None:
    data = msg.to_json()
    assert json.loads(data)["v"] == p.PROTOCOL_VERSION
    assert type(msg).from_json(data) == msg
    assert type(msg).from_json(data.decode()) == msg


def test_ints_accepted_for_floats_and_normalised() -> None:
    grant = m.LeaseGrant(**dict(GRANT, expires_at=5, lease_s=3))
    assert isinstance(grant.expires_at, float) and isinstance(grant.lease_s, float)


def _grant(**changes) -> bytes:
    return json.dumps({"v": 1, **dict(GRANT, **changes)}).encode()


def _start(**changes) -> bytes:
    return _grant(start_state=dict(START, **changes))


def _nested(depth: int) -> dict:
    """An object ``depth`` levels deep: {"a": {"a": ... {} }}."""
    obj: dict = {}
    for _ in range(depth - 1):
        obj = {"a": obj}
    return obj


BAD = [
    # (message class, raw input, expected code)
    (m.LeaseRequest, None, ErrorCode.BAD_JSON),
    (m.LeaseRequest, b"", ErrorCode.BAD_JSON),
    (m.LeaseRequest, b"{not json", ErrorCode.BAD_JSON),
    (m.LeaseRequest, b"\xff\xfe", ErrorCode.BAD_JSON),
    (m.LeaseRequest, b"[1, 2]", ErrorCode.BAD_JSON),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "w", "tasks": NaN}', ErrorCode.BAD_JSON),
    (m.LeaseRequest, b'{"worker_id": "w"}', ErrorCode.BAD_VERSION),
    (m.LeaseRequest, b'{"v": 2, "worker_id": "w"}', ErrorCode.BAD_VERSION),
    (m.LeaseRequest, b'{"v": "1", "worker_id": "w"}', ErrorCode.BAD_VERSION),
    (m.LeaseRequest, b'{"v": true, "worker_id": "w"}', ErrorCode.BAD_VERSION),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "w", "extra": 1}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": ""}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "a/b"}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "a*"}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": 5}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "w", "tasks": "push"}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "w", "shapes": ["hexagon"]}', ErrorCode.BAD_FIELD),
    (m.LeaseRequest, json.dumps({"v": 1, "worker_id": "w", "tasks": ["push"] * 40}).encode(), ErrorCode.BAD_FIELD),
    (m.LeaseRequest, b'{"v": 1, "worker_id": "' + b"w" * p.MAX_MESSAGE_BYTES + b'"}', ErrorCode.TOO_LARGE),
    (m.LeaseGrant, _grant(task="fly"), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(shape="hexagon"), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(policy="teleport"), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(steps=0), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(steps=p.MAX_EPISODE_STEPS + 1), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(steps=5.5), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(steps=True), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(token=0), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(image_size=4), ErrorCode.BAD_FIELD),
    (m.LeaseRequest, json.dumps({"v": 1, "worker_id": "w", "image_size": 2}).encode(), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(image_size=2048), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(lease_s=-1), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(policy_params=[1]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(policy_params={"x": "y" * (p.MAX_OBJECT_BYTES + 1)}), ErrorCode.TOO_LARGE),
    (m.LeaseGrant, _grant(action_prefix=[[1.0]]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(action_prefix=[[1.0, 600.0]]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(action_prefix=[[1.0, 2.0]] * (p.MAX_PREFIX_STEPS + 1)), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(start_state="T"), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(shape="box"), ErrorCode.BAD_FIELD),  # disagrees with the request's shape
    (m.LeaseGrant, _start(agent=[-1.0, 10.0]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(agent=[1.0, 10.0, 3.0]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(object=[256.0, 513.0, 0.0]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(object=[256.0, "x", 0.0]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(agent_vel=[1e9, 0.0]), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(physics={"mass": 100.0}), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(physics={"gravity": 1.0}), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _start(colour="red"), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(start_state={"shape": "T", "agent": [1, 2]}), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(start_state=dict(START, agent=[1e400, 2.0])).replace(b"Infinity", b"1e400"),
     ErrorCode.BAD_FIELD),
    (m.RenewRequest, b'{"v": 1, "request_id": "r", "token": "1", "worker_id": "w"}', ErrorCode.BAD_FIELD),
    (m.RenewRequest, b'{"v": 1, "request_id": "r", "token": -1, "worker_id": "w"}', ErrorCode.BAD_FIELD),
    (m.UploadHeader, b'{"v": 1, "request_id": "r", "token": 1, "worker_id": "w", "sha256": "ab", "size": 3}',
     ErrorCode.BAD_FIELD),
    (m.UploadHeader, json.dumps({"v": 1, "request_id": "r", "token": 1, "worker_id": "w", "sha256": "a" * 64 + "\n",
                                 "size": 3}).encode(), ErrorCode.BAD_FIELD),  # (a `$` check took it)
    (m.UploadHeader, json.dumps({"v": 1, "request_id": "r", "token": 1, "worker_id": "w", "sha256": "a" * 64,
                                 "size": p.MAX_UPLOAD_BYTES + 1}).encode(), ErrorCode.TOO_LARGE),
    (m.FailRequest, json.dumps({"v": 1, "request_id": "r", "token": 1, "worker_id": "w",
                                "error": "e" * (p.MAX_ERROR_CHARS + 1)}).encode(), ErrorCode.BAD_FIELD),
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "max_attempts": 0}).encode(), ErrorCode.BAD_FIELD),
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "priority": "high"}).encode(), ErrorCode.BAD_FIELD),
    # nested deeper than the parser recurses, yet well under MAX_MESSAGE_BYTES: refused, not a crash
    (m.LeaseRequest, b'{"v": 1, "worker_id": ' + b"[" * 1000 + b"]" * 1000 + b"}", ErrorCode.BAD_JSON),
    (m.LeaseRequest, b'{"v": 1, "worker_id": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", ErrorCode.BAD_JSON),
    (m.AdminRequest, b'{"v": 1, "op": "stats", "args": {"a": ' + b"[" * 990 + b"]" * 990 + b"}}", ErrorCode.BAD_JSON),
    # parsed, but nested past MAX_OBJECT_DEPTH: later copies (dataclasses.asdict) would recurse too deep
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "reason": _nested(p.MAX_OBJECT_DEPTH + 1)}).encode(), ErrorCode.BAD_FIELD),
    (m.AdminRequest, json.dumps({"v": 1, "op": "queue.add", "args": {"reason": _nested(600)}}).encode(),
     ErrorCode.BAD_FIELD),
    # an integer literal too large for a float
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "priority": 10 ** 400}).encode(), ErrorCode.BAD_FIELD),
    (m.LeaseGrant, _grant(expires_at=10 ** 400), ErrorCode.BAD_FIELD),
    # half a surrogate pair (escaped or as bytes): no UTF-8 string holds it, so storage could not either
    (m.FailRequest, b'{"v": 1, "request_id": "r", "token": 1, "worker_id": "w", "error": "bad \\ud800 x"}',
     ErrorCode.BAD_JSON),
    (m.FailRequest, b'{"v": 1, "request_id": "r", "token": 1, "worker_id": "w", "error": "bad \xed\xa0\x80"}',
     ErrorCode.BAD_JSON),
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "idempotency_key": "\ud800k"}).encode(), ErrorCode.BAD_JSON),
    # it goes into every grant, where workers allow 128 characters
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START,
                                "reason": {"model_version": "v" * 200}}).encode(), ErrorCode.BAD_FIELD),
    # JSON between systems is UTF-8 (RFC 8259), and the version an integer
    (m.LeaseRequest, '{"v": 1, "worker_id": "w"}'.encode("utf-16"), ErrorCode.BAD_JSON),
    (m.LeaseRequest, '{"v": 1, "worker_id": "w"}'.encode("utf-32-le"), ErrorCode.BAD_JSON),
    (m.LeaseRequest, b'\xef\xbb\xbf{"v": 1, "worker_id": "w"}', ErrorCode.BAD_JSON),
    (m.LeaseRequest, b'{"v": 1.0, "worker_id": "w"}', ErrorCode.BAD_VERSION),
    # too short to learn from (a model needs its context frames and the next): any client, not only the CLI
    (m.RequestSpec, json.dumps({"v": 1, "task": "push", "shape": "T", "start_state": START, "steps": 2}).encode(),
     ErrorCode.BAD_FIELD),
    (m.AdminRequest, b'{"v": 1, "op": "queue.drop"}', ErrorCode.UNKNOWN_OP),
    (m.AdminRequest, b'{"v": 1, "op": "queue.ls", "args": []}', ErrorCode.BAD_FIELD),
    (m.Event, b'{"v": 1, "kind": "request.exploded", "at": 1.0}', ErrorCode.BAD_FIELD),
]


@pytest.mark.parametrize("cls, raw, code", BAD, ids=[f"{i}-{c.__name__}" for i, (c, _, _) in enumerate(BAD)])
def test_malformed_input_refused(cls, raw, code) -> None:
    with pytest.raises(ProtocolError) as info:
        cls.from_json(raw)
    assert info.value.code == code, info.value
    reply = json.loads(info.value.reply())
    assert reply == {"v": 1, "ok": False, "error": code.value, "message": info.value.message}


def test_objects_nested_up_to_the_limit_pass_and_cycles_end() -> None:
    spec = m.RequestSpec(task="push", shape="T", start_state=START, reason=_nested(p.MAX_OBJECT_DEPTH))
    assert m.RequestSpec.from_json(spec.to_json()) == spec
    cycle: dict = {}
    cycle["a"] = cycle
    cycle["b"] = [cycle]
    with pytest.raises(ProtocolError, match="nested at most") as info:
        p.check_obj("reason", cycle)
    assert info.value.code == ErrorCode.BAD_FIELD


def test_construction_validates_too() -> None:
    with pytest.raises(ProtocolError, match="steps"):
        m.LeaseGrant(**dict(GRANT, steps=-3))


def test_upload_payload_checks() -> None:
    payload = b"\x89MCAP0\r\n" + bytes(100)
    header = m.UploadHeader.for_payload(payload, request_id="r1", token=1, worker_id="w")
    assert header.sha256 == hashlib.sha256(payload).hexdigest() and header.size == len(payload)
    assert header.check_payload(memoryview(payload)) == payload
    with pytest.raises(ProtocolError) as info:
        header.check_payload(payload[:-1])
    assert info.value.code == ErrorCode.BAD_FIELD
    with pytest.raises(ProtocolError) as info:
        header.check_payload(payload[:-1] + b"\x01")
    assert info.value.code == ErrorCode.HASH_MISMATCH
    with pytest.raises(ProtocolError) as info:
        header.check_payload(None)
    assert info.value.code == ErrorCode.BAD_FIELD


def test_replies() -> None:
    assert p.parse_reply(p.ok_reply(expires_at=3.0)) == {"expires_at": 3.0}
    assert p.parse_reply(p.duplicate_reply(episode_id="e")) == {"duplicate": True, "episode_id": "e"}
    with pytest.raises(ProtocolError) as info:
        p.parse_reply(p.error_reply(ErrorCode.STALE_TOKEN, "token 1 is not live"))
    assert info.value.code == ErrorCode.STALE_TOKEN and info.value.message == "token 1 is not live"
    with pytest.raises(ProtocolError) as info:
        p.parse_reply(b'{"v": 1, "ok": false, "error": "martian", "message": "?"}')
    assert info.value.code == ErrorCode.INTERNAL
    with pytest.raises(ProtocolError) as info:
        p.parse_reply(b'{"v": 1}')
    assert info.value.code == ErrorCode.BAD_FIELD
    grant = m.LeaseGrant(**GRANT)
    assert m.LeaseGrant.from_dict(p.parse_reply(p.ok_reply(grant=grant.to_dict()))["grant"]) == grant


def test_keys() -> None:
    k = p.Keys("lab/a-1")
    assert (k.lease, k.renew, k.upload, k.fail, k.release) == (
        "lab/a-1/orch/lease", "lab/a-1/orch/renew", "lab/a-1/orch/upload", "lab/a-1/orch/fail", "lab/a-1/orch/release")
    assert k.admin("queue.ls") == "lab/a-1/admin/queue/ls" and k.admin_op("lab/a-1/admin/queue/ls") == "queue.ls"
    assert k.admin_all == "lab/a-1/admin/**"
    assert k.worker("w-1") == "lab/a-1/workers/w-1" and k.worker_id("lab/a-1/workers/w-1") == "w-1"
    assert k.workers_all == "lab/a-1/workers/*" and k.workers_prefix == "lab/a-1/workers"
    assert k.events("request.done") == "lab/a-1/events/request/done" and k.events_all == "lab/a-1/events/**"
    assert k.event_kind("lab/a-1/events/model/promoted") == p.EventKind.MODEL_PROMOTED
    assert p.Keys().lease == "activecollect/orch/lease"
    for op in p.ADMIN_OPS:
        assert k.admin_op(k.admin(op)) == op
    for bad in ("", "a/*", "a/**", "a//b", "/a", "a/", "a b", "a$b", "a?", "a#"):
        with pytest.raises(ProtocolError):
            p.Keys(bad)
    with pytest.raises(ProtocolError):
        k.worker("a/b")
    with pytest.raises(ProtocolError) as info:
        k.admin_op("lab/a-1/admin/queue/drop")
    assert info.value.code == ErrorCode.UNKNOWN_OP


def test_request_seed_is_stable() -> None:
    assert m.request_seed("r1", 1) == m.request_seed("r1", 1) != m.request_seed("r1", 2)
    assert 0 <= m.request_seed("r1", 1) < 2**31


def _imports(module) -> set[str]:
    tree = ast.parse(Path(module.__file__).read_text())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    return imported


def test_protocol_is_a_leaf_module() -> None:
    assert not {name.split(".")[0] for name in _imports(p)} & {"storage", "workers", "uncertainty", "orchestrator"}


def test_messages_import_only_the_protocol() -> None:
    ours = {name for name in _imports(m) if name.split(".")[0] in {"storage", "workers", "uncertainty", "orchestrator"}}
    assert ours == {"orchestrator.protocol"}


def test_escaped_characters_outside_the_basic_plane_still_decode() -> None:
    body = p.decode(b'{"v": 1, "error": "smile \\ud83d\\ude00 and \\u00fc"}')
    assert body == {"error": "smile \U0001F600 and \u00fc"}
    assert p.decode('{"v": 1, "w": "\u00fc"}') == {"w": "\u00fc"}


def test_the_wire_takes_the_frame_sizes_storage_does() -> None:
    from storage import records  # this module imports nothing of ours; the test keeps them equal
    assert (p.MIN_FRAME_SIZE, p.MAX_FRAME_SIZE) == (records.MIN_FRAME_SIZE, records.MAX_FRAME_SIZE)


def test_the_fewest_steps_are_what_training_at_the_default_context_needs() -> None:
    from uncertainty.config import TrainConfig  # this module imports nothing of ours; the test keeps them equal
    assert p.MIN_EPISODE_STEPS == TrainConfig.context + 1
