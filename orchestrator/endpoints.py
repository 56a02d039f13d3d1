"""Zenoh endpoints from the command line: the flags every process that talks Zenoh shares.

``--listen`` / ``--connect`` values are checked for shape (:func:`endpoint_problem`) before Zenoh
sees them, ``--timeout`` for range; :func:`endpoints_from_args` applies the default endpoint and
checks a ``--zenoh-config``'s files first. Sessions and queries are ``orchestrator.transport``'s.

A leaf module like ``orchestrator.transport``, which it imports (and ``orchestrator.locators``, a leaf), so
workers on any host can use it.
"""

from __future__ import annotations

import argparse
import math
import socket
from pathlib import Path

from orchestrator.locators import INET_PROTOCOLS, endpoint_problem, split_endpoint
from orchestrator.transport import (MODES, RX_MAX_MESSAGE_BYTES, RX_MAX_MESSAGE_SIZE_KEY, SecureConfigError,
                                    validate_secure_config)


#: Where ``serve`` listens and everyone else connects when no endpoint or config file is given.
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: Longest ``--timeout`` (a day): Zenoh refuses durations past about 1e19 s, and no one waits longer.
MAX_TIMEOUT_S = 86400.0


def timeout_seconds(text: str) -> float:
    """A ``--timeout``: seconds in (0, MAX_TIMEOUT_S]; nan and inf are refused (argparse exits 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, found {text!r}") from None
    if not (math.isfinite(value) and 0 < value <= MAX_TIMEOUT_S):
        raise argparse.ArgumentTypeError(f"expected seconds in (0, {MAX_TIMEOUT_S:g}], found {text!r}")
    return value


def config_file(text: str) -> Path:
    """A ``--zenoh-config`` (argparse type): an empty path (an unset shell variable) is refused as empty, where
    Path would take it for the current directory and the error would name "."."""
    if not text:
        raise argparse.ArgumentTypeError("expected a Zenoh config file, found an empty path")
    return Path(text)


def with_ports_chosen(listen: tuple[str, ...]) -> tuple[str, ...]:
    """``listen`` with each port 0 (any free port) replaced by one the system picks now, so that what is printed
    is where it listens: Zenoh binds port 0 itself and tells no one which port it got (zenoh-python 1.x has no
    session locators; only Zenoh's admin space, which is off by default and would answer any peer, says).

    A socket is bound at the endpoint's host, port 0, and closed: another process could take that port before
    Zenoh binds it, and then the session fails to open saying so (a port in use). An endpoint whose host cannot
    be bound here is left as it is, for Zenoh to refuse in its own words.
    """
    return tuple(_port_chosen(ep) for ep in listen)


def _port_chosen(text: str) -> str:
    parts = split_endpoint(text)
    if parts.proto not in INET_PROTOCOLS or parts.port != "0":
        return text
    kind = socket.SOCK_DGRAM if parts.proto in ("udp", "quic") else socket.SOCK_STREAM
    try:
        family, _, _, _, where = socket.getaddrinfo(parts.bare_host, 0, type=kind, flags=socket.AI_PASSIVE)[0]
        with socket.socket(family, kind) as sock:
            sock.bind(where)
            chosen = sock.getsockname()[1]
    except (OSError, UnicodeError):
        return text
    return f"{parts.proto}/{parts.host}:{chosen}{text[len(parts.locator):]}"


def keyless_tls_listener(listen: tuple[str, ...], zenoh_config: object) -> str:
    """What is wrong with listening on a ``tls/`` or ``quic/`` endpoint with no config ('' when nothing): the
    listener has no certificate and key to present (Zenoh refuses it at start, "Missing TLS private key"). An
    endpoint carrying its own settings after ``#`` is left to Zenoh."""
    if zenoh_config is not None:
        return ""
    keyless = [ep for ep in listen if ep.startswith(("tls/", "quic/")) and "#" not in ep]
    if not keyless:
        return ""
    return (f"--listen {keyless[0]}: a TLS listener needs a certificate and private key, from a --zenoh-config "
            "(`activecollect secure init` writes a profile with them)")


def endpoint(text: str) -> str:
    """A ``--listen`` / ``--connect`` value (argparse type): a bad shape exits 2 saying what is wrong."""
    problem = endpoint_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def add_connection_args(parser: argparse.ArgumentParser, *, listen: bool = False, timeout: float = 5.0) -> None:
    """The flags every process that talks Zenoh shares: endpoints, config file, namespace, timeout.

    ``listen=True`` (the service) adds ``--listen`` and leaves ``--timeout`` out (the service answers
    queries, it waits on none); ``--connect`` is always there.
    """
    if listen:
        parser.add_argument("--listen", action="append", default=[], metavar="EP", type=endpoint,
                            help=f"Zenoh endpoint to listen on (repeatable; default {DEFAULT_ENDPOINT} "
                                 "when no --connect or --zenoh-config is given)")
    parser.add_argument("--connect", action="append", default=[], metavar="EP", type=endpoint,
                        help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; added after a "
                             "--zenoh-config's own, which a client links to first: to use another router, edit "
                             "the config's connect/endpoints"
                             + ("" if listen else f"; default {DEFAULT_ENDPOINT} without --zenoh-config") + ")")
    parser.add_argument("--zenoh-config", type=config_file, default=None, metavar="FILE",
                        help="Zenoh JSON5 config file, used as written (routers, TLS, passwords, ACL); "
                             f"incoming messages are capped at {RX_MAX_MESSAGE_BYTES >> 20} MiB unless it "
                             f"sets {RX_MAX_MESSAGE_SIZE_KEY}")
    parser.add_argument("--mode", choices=MODES, default="peer",
                        help="Zenoh mode when no config file is given (default peer)")
    parser.add_argument("--namespace", default="activecollect",
                        help="key prefix of the deployment (default activecollect)")
    if not listen:
        parser.add_argument("--timeout", type=timeout_seconds, default=timeout, metavar="S",
                            help=f"seconds to wait for a reply (default {timeout:g})")


def endpoints_from_args(args: argparse.Namespace) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(listen, connect) from :func:`add_connection_args` flags, defaults applied.

    Every process calls this first, so a ``--zenoh-config`` whose certificate, key or
    password file is missing stops it here: raises ``SecureConfigError`` (one line).
    """
    if args.zenoh_config is not None:
        validate_secure_config(args.zenoh_config)
    listen = tuple(getattr(args, "listen", None) or ())
    connect = tuple(args.connect or ())
    if problem := keyless_tls_listener(listen, args.zenoh_config):
        raise SecureConfigError(problem)
    if args.zenoh_config is None and not listen and not connect:
        if hasattr(args, "listen"):
            listen = (DEFAULT_ENDPOINT,)
        else:
            connect = (DEFAULT_ENDPOINT,)
    return listen, connect
