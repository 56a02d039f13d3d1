"""A Zenoh endpoint taken apart: ``PROTOCOL/HOST:PORT[?metadata][#config]`` (an IPv6 host in brackets).

A leaf module: it imports nothing of ours, so ``orchestrator.linkprobe``, ``orchestrator.transport`` and
``orchestrator.endpoints`` (and through them the workers) can all use it. It checks nothing: each caller says
what it accepts of the parts.
"""

from __future__ import annotations

from typing import NamedTuple


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
