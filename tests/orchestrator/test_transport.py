"""orchestrator.transport on real Zenoh sessions over loopback."""

from __future__ import annotations

import json
import threading

import pytest
import zenoh

from orchestrator import transport
from orchestrator.serving import Server
from orchestrator.transport import Incoming, NoReplyError, RemoteError, Response
from tests.conftest import free_port, wait_for


@pytest.fixture
def pair(endpoint: str):
    """A listening 'service' session and a connected 'client' session."""
    server = transport.open_session(listen=[endpoint])
    client = transport.open_session(connect=[endpoint])
    yield server, client
    client.close()
    server.close()


def test_make_config_is_explicit_peer_without_multicast(endpoint: str) -> None:
    config = transport.make_config(listen=[endpoint], connect=["tcp/127.0.0.1:1"])
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/gossip/enabled")) is False  # nor learnt from other peers
    assert json.loads(config.get_json("listen/endpoints")) == [endpoint]
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:1"]


def test_make_config_rejects_unknown_mode_and_lonely_client() -> None:
    with pytest.raises(transport.TransportError, match="mode must be one of"):
        transport.make_config(mode="router")
    with pytest.raises(transport.TransportError, match="client mode needs"):
        transport.make_config(mode="client")


def test_config_file_passes_through_and_flags_add_endpoints(tmp_path, endpoint: str) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text("""{
      // a standard Zenoh config, as an operator would write it
      mode: "client",
      connect: { endpoints: ["tcp/10.0.0.1:7447"] },
      scouting: { multicast: { enabled: true } },
    }""")
    config = transport.make_config(connect=[endpoint], config_file=path)
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is True  # the file wins
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447", endpoint]


def test_bad_config_file_is_a_transport_error(tmp_path) -> None:
    path = tmp_path / "broken.json5"
    path.write_text("{ mode: ")
    with pytest.raises(transport.TransportError, match="not valid JSON5"):
        transport.make_config(config_file=path)


def test_config_file_zenoh_refuses_is_a_transport_error(tmp_path) -> None:
    path = tmp_path / "unknown-key.json5"
    path.write_text('{ mode: "client", no_such_section: { x: 1 } }')
    with pytest.raises(transport.TransportError, match="cannot load Zenoh config"):
        transport.make_config(config_file=path)


def test_config_naming_a_missing_certificate_is_refused(tmp_path) -> None:
    path = tmp_path / "tls.json5"
    path.write_text('{ transport: { link: { tls: { root_ca_certificate: "%s" } } } }' % (tmp_path / "ca.pem"))
    with pytest.raises(transport.SecureConfigError, match="ca.pem is missing"):
        transport.make_config(config_file=path)


def test_request_round_trip_with_attachment_and_large_payload(pair) -> None:
    server_session, client = pair
    seen: list[Incoming] = []

    def echo(msg: Incoming) -> Response:
        seen.append(msg)
        return Response(msg.payload[::-1], attachment=msg.attachment)

    server = Server(server_session, "t/echo", echo)
    try:
        reply = transport.request(client, "t/echo", b"abc", attachment=b"hdr", timeout=5)
        assert reply == Response(b"cba", b"hdr")
        big = bytes(range(256)) * 8192  # 2 MiB: fragmented by Zenoh
        assert transport.query(client, "t/echo", big, timeout=10) == big[::-1]
        assert seen[0].key == "t/echo" and seen[0].attachment == b"hdr"
    finally:
        server.close()


def test_no_reply_when_nobody_serves_the_key(pair) -> None:
    _, client = pair
    with pytest.raises(NoReplyError, match="no reply on t/nobody"):
        transport.query(client, "t/nobody", b"x", timeout=0.3)


def test_no_reply_when_the_queryable_never_answers(pair) -> None:
    server_session, client = pair
    held: list[zenoh.Query] = []
    queryable = server_session.declare_queryable("t/stuck", held.append)
    try:
        with pytest.raises(NoReplyError, match="Timeout"):
            transport.query(client, "t/stuck", b"x", timeout=1.0)
        assert held, "the query reached the queryable"
    finally:
        for q in held:
            q.drop()
        queryable.undeclare()


def test_handler_crashes_get_an_internal_error_reply_and_the_server_stays_up(pair) -> None:
    server_session, client = pair

    def handler(msg: Incoming) -> Response:
        if msg.payload == b"crash":
            raise ZeroDivisionError("boom")
        return Response(b"fine")

    server = Server(server_session, "t/h", handler)
    try:
        body = json.loads(transport.query(client, "t/h", b"crash"))
        assert body["ok"] is False and body["error"] == "internal" and "ZeroDivisionError" in body["message"]
        assert transport.query(client, "t/h", b"ok") == b"fine"
    finally:
        server.close()


def test_a_reply_that_cannot_be_sent_is_an_internal_error_and_the_query_is_not_sent_again(pair) -> None:
    """A handler bug after the handler ran (a reply Zenoh cannot send): answered once, never re-run."""
    server_session, client = pair
    runs = []

    def handler(msg: Incoming) -> Response:
        runs.append(msg.payload)
        return "not a Response" if msg.payload == b"bad" else Response(b"fine")  # type: ignore[return-value]

    server = Server(server_session, "t/r", handler, threads=1)
    try:
        with pytest.raises(transport.RemoteError, match="internal"):
            transport.query(client, "t/r", b"bad")
        assert runs == [b"bad"]  # request() did not take silence for "nobody serving" and send it again
        assert transport.query(client, "t/r", b"ok") == b"fine"  # the one server thread lives
    finally:
        server.close()


def test_remote_error_replies_become_remote_error(pair) -> None:
    server_session, client = pair
    body = json.dumps({"v": 1, "ok": False, "error": "bad", "message": "no thanks"}).encode()
    queryable = server_session.declare_queryable(
        "t/e", lambda q: q.reply_err(body, encoding=transport.ERROR_ENCODING))
    try:
        with pytest.raises(RemoteError) as info:
            transport.query(client, "t/e", b"x")
        assert (info.value.code, info.value.message) == ("bad", "no thanks")
    finally:
        queryable.undeclare()


def test_wildcard_queries_are_refused_before_the_handler_runs(pair) -> None:
    server_session, client = pair
    calls: list[str] = []
    server = Server(server_session, "t/admin/**", lambda m: calls.append(m.key) or Response(b"x"))
    try:
        assert transport.query(client, "t/admin/stats") == b"x"
        with pytest.raises(RemoteError) as info:
            transport.query(client, "t/admin/*")
        assert info.value.code == "bad_field"
        assert calls == ["t/admin/stats"]
    finally:
        server.close()


@pytest.mark.parametrize("threads", [0, 3])  # 0: answered on Zenoh's callback thread
def test_concurrent_requests_all_get_their_own_reply(pair, threads: int) -> None:
    server_session, client = pair
    server = Server(server_session, "t/inc", lambda m: Response(str(int(m.payload) + 1).encode()), threads=threads)
    results: dict[int, int] = {}

    def call(i: int) -> None:
        results[i] = int(transport.query(client, "t/inc", str(i).encode()))

    try:
        threads = [threading.Thread(target=call, args=(i,)) for i in range(40)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert results == {i: i + 1 for i in range(40)}
    finally:
        server.close()


def test_request_waits_for_a_service_that_starts_late(endpoint: str) -> None:
    client = transport.open_session(connect=[endpoint])
    server_session = transport.open_session(listen=[endpoint])
    server = Server(server_session, "t/late", lambda m: Response(b"here"))
    try:
        assert transport.query(client, "t/late", timeout=15) == b"here"
    finally:
        server.close()
        server_session.close()
        client.close()


def test_liveliness_token_loss_is_seen(pair) -> None:
    server_session, client = pair
    events: list[tuple[str, bool]] = []
    sub = server_session.liveliness().declare_subscriber(
        "t/workers/*", lambda s: events.append((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)), history=True)
    token = client.liveliness().declare_token("t/workers/w1")
    wait_for(lambda: ("t/workers/w1", True) in events, message="token appears")
    token.undeclare()
    wait_for(lambda: ("t/workers/w1", False) in events, message="token disappears")
    sub.undeclare()


def test_a_session_zenoh_cannot_open_is_one_line_without_rust_source_locations() -> None:
    closed = f"tcp/127.0.0.1:{free_port()}"  # nobody listens there: a client session cannot open
    with pytest.raises(transport.TransportError) as info:
        transport.open_session("client", connect=[closed])
    message = str(info.value)
    assert closed in message and "\n" not in message and ".rs:" not in message and "/root/" not in message, message


def test_zenoh_error_keeps_the_first_line_less_the_rust_locations() -> None:
    raw = ("Can not create a new TCP listener bound to tcp/8.8.8.8:7447: [8.8.8.8:7447: Cannot assign requested "
           "address (os error 99) at /root/.cargo/git/checkouts/zenoh-9c5/cc8/io/zenoh-link-commons/src/tcp.rs:61.] "
           "at /root/.cargo/git/checkouts/zenoh-9c5/cc8/io/zenoh-links/zenoh-link-tcp/src/unicast.rs:338.\nmore")
    assert transport.zenoh_error(Exception(raw)) == ("Can not create a new TCP listener bound to tcp/8.8.8.8:7447: "
                                                     "[8.8.8.8:7447: Cannot assign requested address (os error 99)]")
    assert transport.zenoh_error(ValueError("")) == "ValueError"


@pytest.mark.parametrize("threads", [0, 2])  # 0: the query is answered on Zenoh's callback thread
def test_close_returns_only_once_the_query_in_hand_is_answered(pair, threads: int) -> None:
    """Zenoh's undeclare() does not wait for a callback in progress; close() does, so that no handler of ours runs
    on what the service closes next (a lease committed on a closed queue, its reply dropped with the session)."""
    server_session, client = pair
    started, release, closed, seen = threading.Event(), threading.Event(), threading.Event(), {}

    def slow(msg: Incoming) -> Response:
        started.set()
        release.wait(60)
        seen["closed before it answered"] = closed.is_set()
        return Response(b"answered")

    server = Server(server_session, "t/slow", slow, threads=threads)
    replies: list[bytes] = []
    asker = threading.Thread(target=lambda: replies.append(transport.query(client, "t/slow", b"", timeout=60)))
    asker.start()
    closer = threading.Thread(target=lambda: (server.close(timeout=60), closed.set()))
    try:
        assert started.wait(30), "the query reached the handler"
        closer.start()
        closed.wait(1.0)  # (a close that does not wait returns at once: it gets this long to)
    finally:
        release.set()
        asker.join(60)
        if closer.is_alive() or not closed.is_set():
            closer.join(60)
    assert seen == {"closed before it answered": False} and replies == [b"answered"]


@pytest.mark.parametrize("threads", [0, 2])
def test_close_says_which_queries_are_still_being_answered_when_its_time_is_up(pair, threads: int, caplog) -> None:
    server_session, client = pair
    started, release = threading.Event(), threading.Event()

    def stuck(msg: Incoming) -> Response:
        started.set()
        release.wait(60)
        return Response(b"late")

    server = Server(server_session, "t/stuck", stuck, threads=threads)
    asker = threading.Thread(target=lambda: transport.query(client, "t/stuck", b"", timeout=60))
    asker.start()
    try:
        assert started.wait(30), "the query reached the handler"
        with caplog.at_level("WARNING", logger="orchestrator.serving"):
            server.close(timeout=0.2)
    finally:
        release.set()
        asker.join(60)
    assert "closing t/stuck: 1 query(ies) still being answered after 0.2 s" in caplog.text
