"""What the operator commands, ``serve``, ``router`` and the worker say about their Zenoh links: a peer that reaches
nothing says so at once, ``serve`` claims no link it does not have, ``--listen ...:0`` prints the port it got, and an
empty ``--zenoh-config`` is refused as empty."""

from __future__ import annotations

import json
import re
import socket
from collections.abc import Iterator

import pytest

from orchestrator import endpoints, linkprobe, transport
from tests.conftest import free_port, run_cli, wait_for
from workers import cli as worker_cli


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port where something takes TCP connections (and never speaks Zenoh)."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(16)
        yield listener.getsockname()[1]


# ---------------------------------------------------------------- linkprobe.unreachable

def test_unreachable_names_every_endpoint_where_nothing_listens() -> None:
    dead = [f"tcp/127.0.0.1:{free_port()}", f"tls/127.0.0.1:{free_port()}"]
    said = linkprobe.unreachable(dead, who="the service")
    assert said == "; ".join(f"nothing listens at {ep} (connection refused): is the service running there?"
                             for ep in dead)


def test_unreachable_is_empty_when_one_endpoint_takes_the_connection(taken_port: int) -> None:
    assert linkprobe.unreachable([f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{taken_port}"]) == ""


@pytest.mark.parametrize("other", ["quic/127.0.0.1:{}", "udp/127.0.0.1:{}", "unixsock-stream//tmp/ac-{}.sock"])
def test_unreachable_cannot_tell_for_endpoints_tcp_cannot_try(other: str) -> None:
    """A TCP probe says nothing of a UDP (quic, udp) or unix-socket listener: such a peer is left to wait."""
    assert linkprobe.unreachable([f"tcp/127.0.0.1:{free_port()}", other.format(free_port())]) == ""


def test_unreachable_cannot_tell_past_the_endpoints_it_tries() -> None:
    many = [f"tcp/127.0.0.1:{free_port()}" for _ in range(linkprobe.MAX_ENDPOINTS + 1)]
    assert linkprobe.unreachable(many) == ""


# ---------------------------------------------------------------- operator commands in peer mode

@pytest.mark.parametrize("argv", [["stats"], ["queue", "ls"], ["watch"]])
def test_a_peer_operator_command_reaching_nothing_says_so_at_once(argv, namespace, capsys) -> None:
    """As a client does: it waited its whole --timeout, then said only that no orchestrator answered."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    rc, out, err = run_cli(capsys, *argv, "--connect", dead, "--namespace", namespace, "--timeout", "20")
    assert rc == 1 and out == "" and err.count("\n") == 1, (rc, out, err)
    assert f"nothing listens at {dead} (connection refused): is `activecollect serve` (or a Zenoh router) running " \
           "there?" in err, err
    assert "no orchestrator answered" not in err


def test_a_peer_operator_command_with_a_quic_endpoint_still_waits_for_an_answer(namespace, capsys) -> None:
    """A quic/ endpoint cannot be tried over TCP: the command waits its --timeout as before."""
    rc, _, err = run_cli(capsys, "stats", "--connect", f"tcp/127.0.0.1:{free_port()}", "--connect",
                         f"quic/127.0.0.1:{free_port()}", "--namespace", namespace, "--timeout", "0.5")
    assert rc == 1 and err.count("\n") == 1 and "no orchestrator answered" in err, err


def test_a_peer_operator_command_reaches_a_peer_on_one_of_its_endpoints(endpoint, namespace, capsys) -> None:
    """One endpoint dead, the other a listening peer (no service on it): it asks, and waits for the answer."""
    peer = transport.open_session(listen=[endpoint])
    try:
        rc, _, err = run_cli(capsys, "stats", "--connect", f"tcp/127.0.0.1:{free_port()}", "--connect", endpoint,
                             "--namespace", namespace, "--timeout", "0.5")
    finally:
        peer.close()
    assert rc == 1 and "no orchestrator answered" in err and "nothing listens" not in err, err


# ---------------------------------------------------------------- serve: connected to, or dialling

def test_unlinked_lists_the_endpoints_without_a_link_and_why(endpoint: str, port: int) -> None:
    dead = f"tcp/127.0.0.1:{free_port()}"
    peer = transport.open_session(listen=[endpoint])
    try:
        session = transport.open_session(connect=[f"tcp/localhost:{port}", dead])
        try:
            assert transport.unlinked(session, [f"tcp/localhost:{port}", endpoint, dead]) == {
                dead: f"nothing listens at {dead} (connection refused): is a Zenoh peer or router running there?"}
        finally:
            session.close()
    finally:
        peer.close()


def _serving_line(proc) -> str:
    return wait_for(lambda: next((ln for ln in proc.log().splitlines() if ln.startswith("serving ")), None),
                    30, "serve's serving line")


def test_serve_says_dialling_for_a_connect_endpoint_nothing_answers(spawn, data_dir, endpoint, namespace) -> None:
    """It said "connected to" an endpoint where nothing listened."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    peer = transport.open_session(listen=[endpoint])
    try:
        serve = spawn("service", "serve", "--data", str(data_dir), "--init", "--namespace", namespace,
                      "--connect", endpoint, "--connect", dead, "--planner", "none", "--dashboard-port", "-1")
        line = _serving_line(serve)
        assert line.startswith(f"serving {namespace} connected to {endpoint}, dialling {dead} (data "), line
        assert (f"no link to --connect {dead} yet (nothing listens at {dead} (connection refused): is a Zenoh peer "
                "or router running there?); Zenoh keeps dialling it") in serve.log()
        assert serve.stop() == 0, serve.log()
    finally:
        peer.close()


def test_a_client_serve_claims_no_dialling_of_the_routers_it_need_not_link_to(spawn, data_dir, namespace) -> None:
    """A client links to one of its routers and dials no other while it has that link: it said "dialling" the
    second router, and warned that Zenoh kept dialling it; then "connected to" both."""
    routers = [f"tcp/127.0.0.1:{free_port()}" for _ in range(2)]
    for i, ep in enumerate(routers):
        router = spawn(f"router{i}", "router", "--listen", ep)
        wait_for(lambda: f" listening on {ep}" in router.log(), 30, "the router's ready line")
    serve = spawn("service", "serve", "--data", str(data_dir), "--init", "--namespace", namespace, "--mode",
                  "client", *(a for ep in routers for a in ("--connect", ep)), "--planner", "none",
                  "--dashboard-port", "-1")
    line = _serving_line(serve)
    assert any(line.startswith(f"serving {namespace} connected to {one} ({other} if that link goes) (data ")
               for one, other in (routers, routers[::-1])), line
    assert "dialling" not in serve.log(), serve.log()
    assert serve.stop() == 0, serve.log()


def test_a_serve_with_a_zenoh_config_in_peer_mode_says_dialling(spawn, data_dir, endpoint, namespace,
                                                                 tmp_path) -> None:
    """The mode of its "serving" line is its --zenoh-config's (here a peer's, --mode client given and ignored)."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "peer.json5"
    config.write_text(json.dumps({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                                  "listen": {"endpoints": [endpoint]}}))
    serve = spawn("service", "serve", "--data", str(data_dir), "--init", "--namespace", namespace, "--mode",
                  "client", "--zenoh-config", str(config), "--connect", dead, "--planner", "none",
                  "--dashboard-port", "-1")
    line = _serving_line(serve)
    assert line.startswith(f"serving {namespace} with Zenoh config {config}, dialling {dead} (data "), line
    assert serve.stop() == 0, serve.log()


def test_serves_mode_is_its_zenoh_configs_as_read_once() -> None:
    """--mode, or its --zenoh-config's as serve read it before the session opened with it (``written``): the file is
    not read again for it (it was, once the session had opened)."""
    from orchestrator.cli.service import _mode
    assert _mode("client", None) == "client"
    assert _mode("client", {"mode": "peer"}) == "peer"
    assert _mode("peer", {"mode": "client", "connect": {"endpoints": []}}) == "client"
    assert _mode("client", {}) == "peer"  # (Zenoh's default)


# ---------------------------------------------------------------- --listen ...:0

def test_ports_chosen_for_port_zero_only() -> None:
    """A port the system picks now, metadata and config kept; a host that is not this machine's is left to Zenoh."""
    chosen = endpoints.with_ports_chosen(("tcp/127.0.0.1:0", "udp/127.0.0.1:0?rel=0#x=1", "tcp/127.0.0.1:7447",
                                "unixsock-stream//tmp/ac.sock", "tcp/192.0.2.1:0"))
    assert re.fullmatch(r"tcp/127\.0\.0\.1:[1-9]\d*", chosen[0]), chosen
    assert re.fullmatch(r"udp/127\.0\.0\.1:[1-9]\d*\?rel=0#x=1", chosen[1]), chosen
    assert chosen[2:] == ("tcp/127.0.0.1:7447", "unixsock-stream//tmp/ac.sock", "tcp/192.0.2.1:0")


def test_serve_listening_on_port_zero_prints_the_port_it_listens_on(spawn, data_dir, namespace, capsys) -> None:
    """It printed tcp/127.0.0.1:0, where no one can connect."""
    serve = spawn("service", "serve", "--data", str(data_dir), "--init", "--namespace", namespace, "--listen",
                  "tcp/127.0.0.1:0", "--planner", "none", "--dashboard-port", "-1")
    line = _serving_line(serve)
    where = re.match(rf"serving {namespace} listening on (tcp/127\.0\.0\.1:(\d+)) \(data ", line)
    assert where and where[2] != "0", line
    rc, out, err = run_cli(capsys, "stats", "--connect", where[1], "--namespace", namespace, "--timeout", "20",
                           "--json")
    assert rc == 0 and "requests" in json.loads(out), err
    assert serve.stop() == 0, serve.log()


def test_router_listening_on_port_zero_prints_the_port_it_listens_on(spawn) -> None:
    router = spawn("router", "router", "--listen", "tcp/127.0.0.1:0")
    line = wait_for(lambda: next((ln for ln in router.log().splitlines() if " listening on " in ln), None),
                    30, "the router's ready line")
    port = re.search(r"listening on tcp/127\.0\.0\.1:(\d+)$", line)
    assert port and port[1] != "0", line
    with socket.create_connection(("127.0.0.1", int(port[1])), timeout=10):
        pass  # it listens there
    assert router.stop() == 0, router.log()


# ---------------------------------------------------------------- --zenoh-config ""

@pytest.mark.parametrize("argv", [["stats"], ["serve"], ["router"], ["worker"], ["secure", "check"]])
def test_an_empty_zenoh_config_is_refused_as_empty(argv, capsys) -> None:
    """It was read as ".": "cannot read Zenoh config . (Is a directory)"."""
    given = [*argv, ""] if argv[0] == "secure" else [*argv, "--zenoh-config", ""]
    rc, out, err = run_cli(capsys, *given)
    assert rc == 2 and out == "" and err.count("\n") == 1, (rc, out, err)
    assert "expected a Zenoh config file, found an empty path" in err and " . " not in err, err


def test_the_worker_agent_refuses_an_empty_zenoh_config_as_empty(capsys) -> None:
    with pytest.raises(SystemExit) as exited:
        worker_cli.main(["--zenoh-config", "", "--once"])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and err == ("python -m workers.agent: error: argument --zenoh-config: expected a "
                                              "Zenoh config file, found an empty path\n"), err
