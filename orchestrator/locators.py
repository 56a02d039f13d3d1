"""A Zenoh endpoint taken apart: ``PROTOCOL/HOST:PORT[?metadata][#config]`` (an IPv6 host in brackets).

A leaf module: it imports nothing of ours, so ``orchestrator.linkprobe``, ``orchestrator.transport`` and
``orchestrator.endpoints`` (and through them the workers) can all use it. ``split_endpoint`` checks nothing: each
caller says what it accepts of the parts; ``endpoint_problem`` says what is wrong with an endpoint's shape.
"""

from __future__ import annotations

from typing import NamedTuple

#: Zenoh's link protocols; the first group's addresses are HOST:PORT.
INET_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
OTHER_PROTOCOLS = ("unixsock-stream",)  # (this build of Zenoh has no unixpipe, serial or vsock links)


class EndpointParts(NamedTuple):
    """The parts of one endpoint, each as written."""

    locator: str
    """The endpoint up to its first ``?`` (metadata) or ``#`` (config): what a link's far end shows."""
    proto: str
    """Before the locator's first ``/``; the whole locator when it has none."""
    host: str
    """Before the address's last ``:`` (an IPv6 host in its brackets); '' when the address has no ``:``."""
    port: str
    """After the address's last ``:``, as written (perhaps not a number); '' when the address has no ``:``."""

    @property
    def port_number(self) -> int | None:
        """``port`` as a number when it is written in ASCII digits, else None (``str.isdigit`` takes '²', which
        ``int`` refuses)."""
        return int(self.port) if self.port.isascii() and self.port.isdigit() else None

    @property
    def bare_host(self) -> str:
        """``host`` without the brackets of an IPv6 host: what a resolver takes."""
        return self.host.removeprefix("[").removesuffix("]")


def split_endpoint(endpoint: str) -> EndpointParts:
    """``endpoint``'s parts (see ``EndpointParts``); what follows the locator is ``endpoint[len(parts.locator):]``."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    proto, _, address = locator.partition("/")
    host, colon, port = address.rpartition(":")
    return EndpointParts(locator, proto, host, port) if colon else EndpointParts(locator, proto, "", "")


def endpoint_problem(text: str) -> str:
    """What is wrong with a Zenoh endpoint's shape ('' when nothing), checked before Zenoh sees it.

    ``PROTOCOL/ADDRESS[?metadata][#config]``; for tcp, udp, tls, quic and ws the address is
    ``HOST:PORT`` (an IPv6 host in brackets) with a port in 0-65535. Zenoh would refuse the rest
    only when the session opens, with a message from its Rust internals.
    """
    proto, slash, rest = text.partition("/")
    if not slash or not proto or not rest:
        return f"expected PROTOCOL/ADDRESS like tcp/10.0.0.5:7447, found {text!r}"
    known = INET_PROTOCOLS + OTHER_PROTOCOLS
    if proto not in known:
        return f"unknown protocol {proto!r} in {text!r}; expected one of {', '.join(known)}"
    if proto in INET_PROTOCOLS:
        parts = split_endpoint(text)
        host = parts.host
        if not host or host in ("[", "[]") or (host.startswith("[") and not host.endswith("]")):
            return f"expected HOST:PORT after {proto}/, found {text!r}"
        if parts.port_number is None or parts.port_number > 65535:
            return f"port must be 0-65535, found {parts.port!r} in {text!r}"
    return ""
