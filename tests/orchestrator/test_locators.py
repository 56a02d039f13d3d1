"""One way to take a Zenoh endpoint apart (``orchestrator.locators.split_endpoint``), and what each of its users
makes of the forms endpoints come in: a peer's link far ends (``transport._locators``), the address ``linkprobe``
dials, the port ``serve`` picks for ``:0`` (``endpoints._port_chosen``), and the shape ``--listen`` checks."""

from __future__ import annotations

import re

import pytest

from orchestrator import endpoints, linkprobe, transport
from orchestrator.locators import EndpointParts, split_endpoint


@pytest.mark.parametrize(("endpoint", "parts", "bare"), [
    ("tcp/127.0.0.1:7447", ("tcp/127.0.0.1:7447", "tcp", "127.0.0.1", "7447"), "127.0.0.1"),
    ("tcp/[::1]:7447", ("tcp/[::1]:7447", "tcp", "[::1]", "7447"), "::1"),
    ("tls/router.example:7447?iface=eth0#root_ca_certificate=/ca.pem",
     ("tls/router.example:7447", "tls", "router.example", "7447"), "router.example"),
    ("tcp/h:7447#a=b?c", ("tcp/h:7447", "tcp", "h", "7447"), "h"),  # (the first of ? and # ends it)
    ("tcp/[::1]:0?a#b", ("tcp/[::1]:0", "tcp", "[::1]", "0"), "::1"),
    ("tcp/h:", ("tcp/h:", "tcp", "h", ""), "h"),
    ("tcp/h", ("tcp/h", "tcp", "", ""), ""),  # no port: no host either
    ("tcp/7447", ("tcp/7447", "tcp", "", ""), ""),
    ("tcp/[::1]", ("tcp/[::1]", "tcp", "[:", "1]"), ":"),  # (the last ':' is taken: callers refuse it)
    ("tcp/h:x7", ("tcp/h:x7", "tcp", "h", "x7"), "h"),
    ("tcp?x/h:1", ("tcp", "tcp", "", ""), ""),
    ("unixsock-stream//tmp/zenoh.sock", ("unixsock-stream//tmp/zenoh.sock", "unixsock-stream", "", ""), ""),
    ("", ("", "", "", ""), ""),
])
def test_split_endpoint(endpoint: str, parts: tuple[str, str, str, str], bare: str) -> None:
    split = split_endpoint(endpoint)
    assert split == EndpointParts(*parts) and split.bare_host == bare
    assert endpoint.startswith(split.locator)


@pytest.mark.parametrize(("port", "number"), [("7447", 7447), ("0", 0), ("", None), ("x7", None), ("\u00b2", None),
                                              ("\u0667", None), ("-1", None), (" 1", None)])
def test_the_port_as_a_number_only_in_ascii_digits(port: str, number: int | None) -> None:
    assert split_endpoint(f"tcp/h:{port}").port_number == number


@pytest.mark.parametrize(("endpoint", "far_ends"), [
    ("tcp/127.0.0.1:7447#x=1", {"tcp/127.0.0.1:7447"}),
    ("tcp/[::1]:7447?iface=lo", {"tcp/[::1]:7447"}),
    ("tcp/localhost:7447", {"tcp/localhost:7447", "tcp/127.0.0.1:7447"}),  # (and ::1 where localhost is that too)
    ("tcp/h:x7", {"tcp/h:x7"}),
    ("tcp/h:\u00b2", {"tcp/h:\u00b2"}),  # (a digit to str.isdigit, not to int: a --zenoh-config's was a traceback)
    ("tcp/h", {"tcp/h"}),
])
def test_the_far_ends_a_link_may_show(endpoint: str, far_ends: set[str]) -> None:
    found = transport._locators(endpoint)
    assert far_ends <= found and found - far_ends <= {"tcp/[::1]:7447"}, found


@pytest.mark.parametrize(("endpoint", "address"), [
    ("tcp/127.0.0.1:7447#x=1", ("tcp", "127.0.0.1", 7447)),
    ("tls/[::1]:7447?iface=lo", ("tls", "::1", 7447)),
    ("tls/router.example:7447", ("tls", "router.example", 7447)),
    ("tcp/:7447", None), ("tcp/h:", None), ("tcp/h", None), ("udp/h:7447", None), ("tcp?x/h:1", None),
    ("tcp/h:\u00b2", None), ("tcp/h:\u0667", None),  # (superscript two, Arabic-Indic seven: not a port)
])
def test_the_address_linkprobe_dials(endpoint: str, address: tuple[str, str, int] | None) -> None:
    assert linkprobe._address(endpoint) == address


@pytest.mark.parametrize(("endpoint", "chosen"), [
    ("tcp/127.0.0.1:0", r"tcp/127\.0\.0\.1:[1-9]\d*"),
    ("udp/127.0.0.1:0?iface=lo#x=1", r"udp/127\.0\.0\.1:[1-9]\d*\?iface=lo#x=1"),
    ("tcp/127.0.0.1:7447", r"tcp/127\.0\.0\.1:7447"),
    ("tcp/127.0.0.1:0x", r"tcp/127\.0\.0\.1:0x"),
    ("unixsock-stream//tmp/zenoh.sock:0", r"unixsock-stream//tmp/zenoh\.sock:0"),
])
def test_the_port_chosen_for_port_zero(endpoint: str, chosen: str) -> None:
    assert re.fullmatch(chosen, endpoints._port_chosen(endpoint))


@pytest.mark.parametrize(("endpoint", "problem"), [
    ("tcp/[::1]:7447?iface=lo", ""), ("tls/h.example:0#x=1", ""),
    ("tcp/h", "expected HOST:PORT"), ("tcp/:7447", "expected HOST:PORT"), ("tcp/[]:7447", "expected HOST:PORT"),
    ("tcp/[::1:7447", "expected HOST:PORT"), ("tcp/h:x7", "port must be 0-65535"), ("tcp/h:65536", "port must be"),
])
def test_the_shape_of_an_endpoint(endpoint: str, problem: str) -> None:
    said = endpoints.endpoint_problem(endpoint)
    assert said.startswith(problem) if problem else said == "", said
