"""Zenoh's own cap on one incoming message (``transport.RX_MAX_MESSAGE_BYTES``), on real sessions over loopback."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest
import zenoh

from orchestrator import transport
from orchestrator.protocol import MAX_MESSAGE_BYTES, MAX_UPLOAD_BYTES, Keys
from orchestrator.serving import Server
from orchestrator.transport import RX_MAX_MESSAGE_BYTES, RX_MAX_MESSAGE_SIZE_KEY, Incoming, Response


def remote_peer(endpoint: str) -> zenoh.Session:
    """A peer connected to ``endpoint`` that never hands messages over in shared memory: on loopback,
    the path a worker on another host takes (Zenoh fragments a big message and the receiver reassembles it)."""
    config = transport.make_config(connect=[endpoint])
    config.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(config)


@pytest.fixture
def service(endpoint: str, namespace: str) -> Iterator[list[tuple[int, int]]]:
    """A session listening on ``endpoint`` as the service opens it, serving the upload key.

    Yields the (payload, attachment) sizes its handler saw, in order; each reply is the payload size.
    """
    session = transport.open_session(listen=[endpoint])
    seen: list[tuple[int, int]] = []

    def sizes(msg: Incoming) -> Response:
        seen.append((len(msg.payload), len(msg.attachment or b"")))
        return Response(str(len(msg.payload)).encode())

    server = Server(session, Keys(namespace).upload, sizes, threads=0)
    yield seen
    server.close()
    session.close()


def test_the_cap_is_above_the_largest_upload_and_in_every_config_we_build() -> None:
    assert RX_MAX_MESSAGE_BYTES >= MAX_UPLOAD_BYTES + MAX_MESSAGE_BYTES  # payload and the largest attachment
    assert RX_MAX_MESSAGE_BYTES <= 2 * MAX_UPLOAD_BYTES  # "a little above", not Zenoh's 1 GiB
    for mode, connect in (("peer", ()), ("client", ("tcp/127.0.0.1:1",))):
        config = transport.make_config(mode, connect=connect)
        assert json.loads(config.get_json(RX_MAX_MESSAGE_SIZE_KEY)) == RX_MAX_MESSAGE_BYTES


def test_a_config_file_gets_the_cap_unless_it_sets_its_own(tmp_path) -> None:
    plain = tmp_path / "plain.json5"
    plain.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.0.0.1:7447"] } }')
    config = transport.make_config(config_file=plain)
    assert json.loads(config.get_json(RX_MAX_MESSAGE_SIZE_KEY)) == RX_MAX_MESSAGE_BYTES

    own = tmp_path / "own.json5"
    own.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.0.0.1:7447"] },\n'
                   '  transport: { link: { rx: { max_message_size: 1048576 } } } }')
    config = transport.make_config(connect=["tcp/127.0.0.1:1"], config_file=own)
    assert json.loads(config.get_json(RX_MAX_MESSAGE_SIZE_KEY)) == 1048576  # the operator's choice stands


def test_a_message_over_the_cap_never_reaches_the_handler_and_the_service_keeps_answering(
        endpoint: str, namespace: str, service: list[tuple[int, int]]) -> None:
    key = Keys(namespace).upload
    sender = remote_peer(endpoint)
    fresh = None
    try:
        assert transport.query(sender, key, b"hello", timeout=10) == b"5"  # connected and declared
        pending = sender.get(key, payload=bytes(RX_MAX_MESSAGE_BYTES + 1), timeout=1.0)
        # Sent after the big one over the same link and priority, so answered only once all of it
        # has arrived: had Zenoh delivered the big one, the handler would have seen it first.
        assert transport.query(sender, key, b"after", timeout=10) == b"5"
        replies = list(pending)  # ends at the get's timeout: Zenoh tells the sender nothing
        assert [r.ok for r in replies if r.ok is not None] == []
        assert [r.err.payload.to_bytes() for r in replies] == [b"Timeout"]
        assert service == [(5, 0), (5, 0)]

        fresh = transport.open_session(connect=[endpoint])
        assert transport.query(fresh, key, b"fresh peer", timeout=10) == b"10"
        assert transport.query(sender, key, b"same peer", timeout=10) == b"9"  # its link survived
        assert service == [(5, 0), (5, 0), (10, 0), (9, 0)]
    finally:
        if fresh is not None:
            fresh.close()
        sender.close()


def test_the_largest_upload_with_the_largest_attachment_gets_through(
        endpoint: str, namespace: str, service: list[tuple[int, int]]) -> None:
    sender = remote_peer(endpoint)
    try:
        reply = transport.query(sender, Keys(namespace).upload, bytes(MAX_UPLOAD_BYTES),
                                attachment=bytes(MAX_MESSAGE_BYTES), timeout=30)
        assert reply == str(MAX_UPLOAD_BYTES).encode()
        assert service == [(MAX_UPLOAD_BYTES, MAX_MESSAGE_BYTES)]
    finally:
        sender.close()
