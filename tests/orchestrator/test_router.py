"""`activecollect router`: a real Zenoh router process that clients (and other routers) go through."""

from __future__ import annotations

import json
import signal
import socket
import sys

import pytest
import zenoh

from orchestrator import transport
from orchestrator.cli import main
from orchestrator.router import DEFAULT_LISTEN, RouterConfig, RouterError, build_router_config, listen_endpoints
from orchestrator.secure import SecureInitConfig, init_secure
from tests.conftest import free_port, wait_for
from tests.orchestrator.test_secure import Proc, activecollect, get_payloads


def client(*connect: str) -> zenoh.Session:
    """A client-mode session: it can only reach others through a router."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def start(*args: str) -> Proc:
    """``activecollect router ARGS`` as its own process, once it listens."""
    return Proc(activecollect("router", *args)).started()


def start_plain_router(listen: tuple[str, ...]) -> Proc:
    """A router without the CLI around it (cheaper to start; the CLI is tested on the other end)."""
    return Proc([sys.executable, "-c", PLAIN_ROUTER, json.dumps(listen)]).started()


PLAIN_ROUTER = """
import json, sys
from orchestrator.router import RouterConfig, run_router
sys.exit(run_router(RouterConfig(listen=json.loads(sys.argv[1])), out=sys.stdout))
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_router_routes_between_clients_and_stops_on_signal(procs, sig):
    """Two client-mode sessions (they cannot reach each other directly) talk through the router."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start("--listen", endpoint)
    procs.append(router)
    assert endpoint in router.lines[-1]
    server, asker = client(endpoint), client(endpoint)
    try:
        queryable = server.declare_queryable("demo/ping", lambda q: q.reply(q.key_expr, b"pong"))
        wait_for(lambda: get_payloads(asker, "demo/ping", timeout=1.0) == [b"pong"], 10, "a reply via the router")
        queryable.undeclare()
    finally:
        asker.close()
        server.close()
    router.popen.send_signal(sig)
    assert router.popen.wait(15) == 0, router.output()


def test_routers_of_two_sites_link_up(procs):
    site_a, site_b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    procs.append(start_plain_router(listen=(site_a,)))
    procs.append(start("--listen", site_b, "--connect", site_a))
    worker_side, orchestrator_side = client(site_b), client(site_a)
    try:
        queryable = orchestrator_side.declare_queryable("demo/lease", lambda q: q.reply(q.key_expr, b"lease"))
        wait_for(lambda: get_payloads(worker_side, "demo/lease", timeout=1.0) == [b"lease"], 15,
                   "a reply across two routers")
        queryable.undeclare()
    finally:
        worker_side.close()
        orchestrator_side.close()


def _run(capsys, *args: str) -> tuple[int, list[str]]:
    """``activecollect router ARGS`` in this process (the error paths return before serving)."""
    try:
        code = main(["router", *args])
    except SystemExit as exc:  # a usage error argparse itself reports
        code = exc.code
    return code, capsys.readouterr().err.strip().splitlines()


def test_router_refuses_bad_endpoint_with_exit_2(capsys):
    code, err = _run(capsys, "--listen", "nowhere")
    assert code == 2 and len(err) == 1 and "expected PROTOCOL/ADDRESS" in err[0]


def test_router_refuses_port_in_use_with_exit_1(capsys):
    """Not a usage error: exit 1, as `serve` on a port in use (a router already there, say)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        code, err = _run(capsys, "--listen", f"tcp/127.0.0.1:{taken.getsockname()[1]}")
    assert code == 1 and len(err) == 1 and "cannot start the router" in err[0] and "in use" in err[0], err


def test_secure_profile_refuses_an_added_plaintext_listener(tmp_path, capsys):
    secure = init_secure(SecureInitConfig(tmp_path / "p", router_endpoint=f"tls/127.0.0.1:{free_port()}"))
    with pytest.raises(RouterError, match="TLS-only"):
        build_router_config(RouterConfig(listen=("tcp/0.0.0.0:7447",), zenoh_config=secure.configs["router"]))
    code, err = _run(capsys, "--zenoh-config", str(secure.configs["router"]), "--listen", "tcp/127.0.0.1:1")
    assert code == 2 and len(err) == 1 and "refusing plaintext endpoint" in err[0]


def test_router_config_defaults_to_loopback_and_keeps_file_endpoints(tmp_path):
    assert listen_endpoints(build_router_config(RouterConfig())) == [DEFAULT_LISTEN]
    secure = init_secure(SecureInitConfig(tmp_path / "p", router_endpoint="tls/127.0.0.1:7999"))
    config = build_router_config(RouterConfig(zenoh_config=secure.configs["router"]))
    assert listen_endpoints(config) == ["tls/127.0.0.1:7999"]
    more = build_router_config(RouterConfig(zenoh_config=secure.configs["router"], listen=("tls/127.0.0.1:7998",)))
    assert listen_endpoints(more) == ["tls/127.0.0.1:7998"]  # replaces the file's: one profile, two routers
    assert json.loads(config.get_json("mode")) == "router"
    for built in (build_router_config(RouterConfig()), config):  # it relays only messages it took in whole
        assert json.loads(built.get_json(transport.RX_MAX_MESSAGE_SIZE_KEY)) == transport.RX_MAX_MESSAGE_BYTES
