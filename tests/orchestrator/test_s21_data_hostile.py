"""Well-formed JSON that is still wrong, sent at every worker key while requests are leased: each gets an error
reply and the SQLite rows (requests and episodes) are byte for byte what they were."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import pytest

from orchestrator import messages, protocol, transport
from orchestrator.protocol import ErrorCode, ProtocolError
from tests.orchestrator.test_service import episode_bytes, lease, new_request, upload


def _rows(data_dir: Path) -> tuple[list[tuple], list[tuple]]:
    conn = sqlite3.connect(data_dir / "catalog.sqlite")
    try:
        return (conn.execute("SELECT * FROM requests ORDER BY id").fetchall(),
                conn.execute("SELECT * FROM episodes ORDER BY episode_id").fetchall())
    finally:
        conn.close()


def _lease_refs(mine: dict[str, Any], other: dict[str, Any]) -> list[dict[str, Any]]:
    """Lease references no live lease matches, or that are malformed: each must be refused."""
    rid, token = mine["request_id"], mine["token"]
    return [
        {**mine, "worker_id": "w2"},  # another worker's id
        {**mine, "request_id": other["request_id"]},  # another request (leased by w2)
        {**mine, "token": token + 1}, {**mine, "token": token + 7},  # tokens from the future
        {**mine, "token": 0}, {**mine, "token": -1}, {**mine, "token": 2**63},
        {**mine, "token": str(token)}, {**mine, "token": float(token)}, {**mine, "token": True},
        {**mine, "token": None}, {**mine, "token": [token]}, {**mine, "token": 1e308},
        {**mine, "request_id": rid + "/*"}, {**mine, "request_id": "r" * 129}, {**mine, "request_id": ""},
        {**mine, "request_id": 7}, {**mine, "request_id": "no-such-request"},
        {**mine, "worker_id": "w1 "}, {**mine, "worker_id": "w" * 10_000}, {**mine, "worker_id": None},
        {**mine, "extra": 1}, {k: v for k, v in mine.items() if k != "token"},
        {k: v for k, v in mine.items() if k != "worker_id"},
    ]


def _send(client, key: str, obj: dict[str, Any] | bytes, payload: bytes = b"") -> ErrorCode:
    raw = obj if isinstance(obj, bytes) else protocol.encode({"v": 1, **obj})
    if key.endswith("/upload"):
        reply = transport.query(client, key, payload, raw, timeout=10)
    else:
        reply = transport.query(client, key, raw, timeout=10)
    with pytest.raises(ProtocolError) as info:
        protocol.parse_reply(reply)
    return info.value.code


def test_hostile_messages_at_leased_requests_get_errors_and_change_no_row(service, client, keys, data_dir) -> None:
    for _ in range(2):
        service.queue.enqueue(new_request())
    g1, g2 = lease(client, keys, worker="w1"), lease(client, keys, worker="w2")
    mine = {"request_id": g1.request_id, "token": g1.token, "worker_id": "w1"}
    other = {"request_id": g2.request_id, "token": g2.token, "worker_id": "w2"}
    data = episode_bytes(g1)
    header = messages.UploadHeader.for_payload(data, request_id=g1.request_id, token=g1.token,
                                               worker_id="w1").to_dict()
    before = _rows(data_dir)
    codes: list[ErrorCode] = []
    for ref in _lease_refs(mine, other):
        codes += [_send(client, keys.renew, ref), _send(client, keys.release, ref),
                  _send(client, keys.fail, {**ref, "error": "boom"})]
        codes.append(_send(client, keys.upload, {**ref, "sha256": header["sha256"], "size": header["size"]}, data))
    for error in ("", "x" * (protocol.MAX_ERROR_CHARS + 1), 7, None, ["boom"]):
        codes.append(_send(client, keys.fail, {**mine, "error": error}))
    nan = protocol.encode({"v": 1, **mine, "error": "boom"}).replace(b'"boom"', b"NaN")
    codes += [_send(client, keys.fail, nan), _send(client, keys.renew, nan.replace(b',"error":NaN', b',"x":Infinity'))]
    for change in ({"size": -1}, {"size": 0}, {"size": header["size"] + 1}, {"size": 2**40},
                   {"size": float(header["size"])}, {"sha256": header["sha256"].upper()}, {"sha256": "0" * 64},
                   {"sha256": None}):
        codes.append(_send(client, keys.upload, {**header, **change}, data))
    codes.append(_send(client, keys.upload, header, data[:-1]))  # the bytes cut short
    codes.append(_send(client, keys.upload, header, b""))
    for ask in ({"worker_id": "w1", "tasks": ["fly"]}, {"worker_id": "w1", "shapes": "box"},
                {"worker_id": "w1", "shapes": ["box"] * 1000}, {"worker_id": "w1", "image_size": 7},
                b'{"v": 1, "worker_id": "w1", "image_size": 1e309}',  # (1e309 is a float infinity to Python's json)
                {"worker_id": "w1", "image_size": -16},
                {"worker_id": "w9", "capabilities": {}}, {"tasks": ["push"]}, {"worker_id": ["w1"]}):
        codes.append(_send(client, keys.lease, ask))
    assert set(codes) <= {ErrorCode.BAD_FIELD, ErrorCode.BAD_JSON, ErrorCode.STALE_TOKEN, ErrorCode.TOO_LARGE,
                          ErrorCode.UNKNOWN_REQUEST, ErrorCode.HASH_MISMATCH}, codes
    assert _rows(data_dir) == before
    assert not list((data_dir / "episodes").rglob("*.mcap"))
    # the real holders still can: nothing above took their leases
    assert protocol.parse_reply(transport.query(client, keys.upload, data, protocol.encode({"v": 1, **header}),
                                                timeout=10))["request_id"] == g1.request_id
    release = messages.ReleaseRequest(**other).to_json()
    assert protocol.parse_reply(transport.query(client, keys.release, release, timeout=10))["status"] == "queued"


def test_a_copy_of_a_stored_upload_under_another_workers_id_is_refused_not_acknowledged(service, client, keys,
                                                                                        data_dir) -> None:
    """The bytes w1 uploaded, sent again under w2's id (w2 never held the lease): a stale token, not a
    "duplicate" that would tell w2 its upload was stored; the repeat from w1 itself is still acknowledged."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    before = _rows(data_dir)
    with pytest.raises(ProtocolError) as info:
        upload(client, keys, grant, data, worker="w2")
    assert info.value.code == ErrorCode.STALE_TOKEN and "held by w1" in info.value.message, info.value
    assert _rows(data_dir) == before
    assert upload(client, keys, grant, data) == {**body, "duplicate": True}
    assert service.queue.get(request.id).worker_id == "w1"
