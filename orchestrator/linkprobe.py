"""Why a Zenoh client could not connect, found by connecting again by hand (``transport.open_session`` asks);
and whether anything at all takes a TCP connection where a peer dials (``unreachable``).

Zenoh says the same "Unable to connect to any of [...]" whether nothing listens at the router's address, the
router refuses this config's certificate, or it took the TLS connection and then refused the login (wrong
user or password: its close message comes in answer to the handshake's OpenSyn and is written only to Zenoh's
own log). Each endpoint is tried again here, one step at a time, with Python's ``socket`` and ``ssl``:

1. TCP: refused (nothing listens), no answer in ``CONNECT_TIMEOUT_S`` (a host down or a firewall), a name that
   does not resolve;
2. for ``tls/``, the handshake with the config's CA, certificate and key: the router's certificate refused by
   this side (another CA, another name), or this side's refused by the router (an alert right after the
   handshake, within ``ALERT_WAIT_S``, TLS 1.3 sending it only then);
3. all of that taken: what is left is Zenoh's own handshake, where the router checks the user and password.

A leaf module like ``orchestrator.transport``: it imports nothing of ours but ``orchestrator.locators`` (a leaf).
Only called when a session failed to open, so the normal start pays nothing.
"""

from __future__ import annotations

import socket
import ssl
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from orchestrator.locators import split_endpoint

#: Seconds to wait for a TCP connection (and then the TLS handshake) to an endpoint.
CONNECT_TIMEOUT_S = 3.0
#: Seconds to wait after a TLS 1.3 handshake for the router's alert that it refuses this side's certificate.
ALERT_WAIT_S = 1.0
#: Most endpoints tried: a config naming more says what the first ones gave.
MAX_ENDPOINTS = 3


@dataclass(frozen=True)
class ClientTls:
    """The TLS settings a Zenoh client connects with (``transport/link/tls/*`` of its config)."""

    root_ca: Path | None = None
    """CA file that must have signed the router's certificate; None: the system's CAs."""
    certificate: Path | None = None
    """This side's certificate (mutual TLS); None: none is presented."""
    private_key: Path | None = None
    """Its key."""
    verify_name: bool = True
    """Whether the router's certificate must name the host connected to."""


def diagnose(endpoints: Sequence[str], tls: ClientTls, user: str | None, config: str | None) -> str:
    """What stops a Zenoh client reaching ``endpoints`` ('' when no endpoint can be tried: none is tcp/ or tls/).

    ``user``: the usrpwd user the config logs in as (None: no login); ``config``: the config file's path, for the
    message. One line, the endpoints' findings joined by '; '.
    """
    found = [f for ep in endpoints[:MAX_ENDPOINTS] if (f := _endpoint(ep, tls, user, config))]
    return "; ".join(found)


def _address(endpoint: str) -> tuple[str, str, int] | None:
    """(protocol, host, port) of a tcp/ or tls/ endpoint, brackets taken off an IPv6 host; None for others."""
    parts = split_endpoint(endpoint)
    if parts.proto not in ("tcp", "tls") or parts.port_number is None or not parts.host:
        return None
    return parts.proto, parts.bare_host, parts.port_number


def unreachable(endpoints: Sequence[str], timeout: float = CONNECT_TIMEOUT_S, who: str = "the router") -> str:
    """Why nothing takes a TCP connection at any of ``endpoints`` (one line, their findings joined by '; '); ''
    when one does, or when one cannot be tried that way (not tcp/ or tls/: quic and udp are UDP, a unix socket is
    no address) or there are more than ``MAX_ENDPOINTS``: then it cannot be told that nothing answers.

    ``timeout``: seconds to wait for each connection, at most ``CONNECT_TIMEOUT_S``; ``who``: what should listen
    there, for the message. A Zenoh peer's session opens whether or not its connect endpoints answer (it keeps
    dialling them): ``transport.open_session`` asks this when one opened with no link.
    """
    if not endpoints or len(endpoints) > MAX_ENDPOINTS:
        return ""
    found = []
    for ep in endpoints:
        address = _address(ep)
        if address is None:
            return ""
        tried = _connect(ep, address[1], address[2], min(timeout, CONNECT_TIMEOUT_S), who)
        if isinstance(tried, socket.socket):
            tried.close()
            return ""
        found.append(tried)
    return "; ".join(found)


def _connect(endpoint: str, host: str, port: int, timeout: float, who: str = "the router") -> socket.socket | str:
    """A TCP connection to ``host``:``port``, or why there is none."""
    try:
        return socket.create_connection((host, port), timeout=timeout)
    except socket.gaierror as exc:
        return f"cannot resolve the host of {endpoint} ({exc.strerror})"
    except TimeoutError:
        return (f"nothing answers at {endpoint} within {timeout:g} s (the host is down or a firewall "
                f"drops the connection)")
    except ConnectionRefusedError:
        return f"nothing listens at {endpoint} (connection refused): is {who} running there?"
    except OSError as exc:
        return f"cannot reach {endpoint} ({exc.strerror or exc})"


def _endpoint(endpoint: str, tls: ClientTls, user: str | None, config: str | None) -> str:
    address = _address(endpoint)
    if address is None:
        return ""
    proto, host, port = address
    sock = _connect(endpoint, host, port, CONNECT_TIMEOUT_S)
    if isinstance(sock, str):
        return sock
    with sock:
        if proto == "tls":
            refused = _tls_refusal(sock, endpoint, host, tls)
            if refused:
                return refused
        return _login_refused(endpoint, proto, user, config)


def _login_refused(endpoint: str, proto: str, user: str | None, config: str | None) -> str:
    where = config or "the config"
    login = (f"check the user ({user!r}) and password in {where}" if user else
             f"it may ask for a user and password, which {where} does not give")
    if proto == "tcp":  # a TLS listener takes the TCP connection too: no telling the two apart without TLS
        return (f"something at {endpoint} accepts TCP connections but refused the Zenoh session: a router that "
                f"asks for TLS there (tls/ endpoints), or one that refused the login ({login})")
    refused = "the login" if user else "the session"
    return (f"the router at {endpoint} accepted the TLS connection and this side's certificate but refused "
            f"{refused}: {login}")


def _tls_refusal(sock: socket.socket, endpoint: str, host: str, tls: ClientTls) -> str:
    """Why the TLS handshake over ``sock`` fails, or the router refuses this side's certificate after it; ''
    when the router took the connection."""
    try:
        context = _context(tls)
    except (OSError, ssl.SSLError) as exc:  # (the start-up check read these files a moment ago)
        return f"cannot load the TLS files to try {endpoint} ({exc})"
    try:
        conn = context.wrap_socket(sock, server_hostname=host)
    except ssl.SSLCertVerificationError as exc:
        ca = tls.root_ca or "the system's CAs"
        return (f"the router at {endpoint} presented a certificate this side does not accept "
                f"({exc.verify_message}; CA {ca})")
    except (ssl.SSLError, OSError) as exc:
        return f"the TLS handshake with {endpoint} failed ({_reason(exc)}): is a TLS router listening there?"
    mine = tls.certificate or "none"
    with conn:
        conn.settimeout(ALERT_WAIT_S)
        try:
            data = conn.recv(1)  # a Zenoh router says nothing before our handshake message: only an alert comes
        except TimeoutError:
            return ""
        except (ssl.SSLError, OSError) as exc:
            return f"the router at {endpoint} refused this side's certificate ({_reason(exc)}; certificate {mine})"
    if data:
        return ""
    return (f"the router at {endpoint} closed the connection right after the TLS handshake: it may refuse this "
            f"side's certificate ({mine})")


def _context(tls: ClientTls) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = tls.verify_name
    if tls.root_ca is not None:
        context.load_verify_locations(tls.root_ca)
    else:
        context.load_default_certs()
    if tls.certificate is not None:
        context.load_cert_chain(tls.certificate, tls.private_key)
    return context


def _reason(exc: BaseException) -> str:
    if isinstance(exc, ssl.SSLError) and exc.reason:
        return exc.reason.lower().replace("_", " ")
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
