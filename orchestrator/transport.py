"""Zenoh plumbing shared by the service, the workers and the operator CLI.

A leaf module: it imports nothing else of ours but ``orchestrator.linkprobe`` and ``orchestrator.locators`` (leaves
too), so workers on any host can use it. It knows bytes, keys and endpoints, not the JSON messages riding on them
(those are the business of ``orchestrator.protocol`` and ``orchestrator.messages``). The command-line flags that name
endpoints, a config file and a timeout live in ``orchestrator.endpoints``.

Two things about zenoh-python 1.x shape this module:

- A query's *final* reply (the "no more replies" marker) is sent when the ``zenoh.Query`` object is dropped. A query
  left alive in Python keeps the querier waiting until its timeout, so ``serving.Server`` replies and then drops every
  query explicitly, whatever the handler did.
- A ``get`` towards a key nobody serves (yet) ends at once with no reply, and a ``get`` whose queryable never
  answers ends at its timeout with a ``ReplyError`` whose payload is ``Timeout``. :func:`request` turns both into
  :class:`NoReplyError`; the first is retried until the deadline, because declarations propagate asynchronously
  right after a session opens or a peer reconnects.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import json5
import zenoh

from orchestrator import linkprobe
from orchestrator.locators import endpoint_problem, split_endpoint

log = logging.getLogger(__name__)

#: Encoding of error replies we send; zenoh's own errors (``Timeout``) carry another one.
ERROR_ENCODING = "application/json"
MODES = ("peer", "client")


class TransportError(Exception):
    """Root of every error raised by ``orchestrator.transport``."""


class NoReplyError(TransportError):
    """Nobody answered a query before its deadline (no service, or it is unreachable or stuck)."""


class RemoteError(TransportError):
    """The remote side answered with an error reply.

    ``payload`` is the raw error body; ``code`` and ``message`` are read from it when it is a JSON object
    (``{"code": ..., "message": ...}``, possibly nested under ``"error"``), else ``code`` is ``"remote"`` and
    ``message`` the text.
    """

    def __init__(self, key: str, payload: bytes) -> None:
        self.key = key
        self.payload = payload
        self.code, self.message = _parse_error(payload)
        super().__init__(f"{key}: {self.code}: {self.message}")


#: Where in Zenoh's Rust source an error was made (`` at /root/.cargo/.../unicast.rs:338.``): noise to a user.
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")


def zenoh_error(exc: BaseException) -> str:
    """What a Zenoh error says, for a user: its first line, without the Rust source locations."""
    text = str(exc).strip()
    text = _RUST_LOCATION.sub("", text.splitlines()[0] if text else "").strip()
    return text or type(exc).__name__


# ---------------------------------------------------------------- config files

#: The largest Zenoh config file read (a secure profile's router.json5 is ~7 KB): a device such as
#: /dev/zero given for one would otherwise be read for ever.
MAX_CONFIG_BYTES = 1 << 20
#: Config keys (slash paths) whose values are files Zenoh opens at start-up.
FILE_KEYS: tuple[str, ...] = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/connect_private_key",
    "transport/link/tls/connect_certificate",
    "transport/auth/usrpwd/dictionary_file",
    "transport/auth/pubkey/public_key_file",
    "transport/auth/pubkey/private_key_file",
    "transport/auth/pubkey/known_keys_file",
)


class SecureConfigError(TransportError):
    """A secure profile cannot be written or started; the message is one line naming the file."""


def lookup_key(config: dict[str, Any], slash_key: str) -> Any:
    """The value at a slash path (``transport/link/tls/...``) of a parsed config, or None."""
    node: Any = config
    for part in slash_key.split("/"):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _check_file(config_path: Path, key: str, value: Any) -> Path:
    if not isinstance(value, str) or not value:
        raise SecureConfigError(f"{config_path}: expected a file path at {key}, found {value!r}")
    path = Path(value).expanduser()
    what = f"{config_path}: {key} -> {path}"
    if not path.exists():
        raise SecureConfigError(f"{what} is missing")
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError as exc:
        raise SecureConfigError(f"{what} is unreadable ({exc.strerror})") from exc
    if key.startswith("transport/link/tls/") and b"-----BEGIN " not in head:
        raise SecureConfigError(f"{what} is not a PEM file")
    if key.endswith("dictionary_file") and not any(b":" in line for line in head.splitlines()):
        raise SecureConfigError(f"{what} holds no user:password line")
    return path


def validate_secure_config(path: str | os.PathLike[str]) -> list[Path]:
    """Checks a Zenoh JSON5 config before a process starts with it; returns the files it references.

    Every endpoint it lists must have a valid shape (``endpoint_problem``). Every file the config names (TLS CA,
    certificates and keys, the usrpwd dictionary, pubkey files) must exist and be readable; TLS files must be PEM,
    and hold certificates a TLS handshake would take (``_check_tls``). A config naming no files passes (it is not
    a secure profile). Raises SecureConfigError with a one-line message naming
    the config, the key and the file or endpoint; CLIs turn it into exit status 2.
    """
    config_path = Path(path)
    return _check_config(config_path, read_config(config_path))


def read_config(config_path: Path) -> dict[str, Any]:
    """The JSON5 object in a Zenoh config file; SecureConfigError (one line) when there is none (also for a file
    that is not UTF-8 text, or one past ``MAX_CONFIG_BYTES``, such as a device that never ends)."""
    try:
        with open(config_path, "rb") as f:
            raw = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise SecureConfigError(f"cannot read Zenoh config {config_path} ({exc.strerror or exc})") from exc
    if len(raw) > MAX_CONFIG_BYTES:
        raise SecureConfigError(f"{config_path} is not a Zenoh config: more than {MAX_CONFIG_BYTES >> 20} MiB")
    try:
        text = raw.decode()
    except UnicodeDecodeError as exc:
        raise SecureConfigError(f"{config_path} is not a Zenoh config: not UTF-8 text ({exc.reason} at byte "
                                f"{exc.start})") from None
    try:
        config = json5.loads(text)
    except ValueError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SecureConfigError(f"{config_path} is not valid JSON5: {first}") from exc
    if not isinstance(config, dict):
        raise SecureConfigError(f"{config_path}: expected a JSON5 object, found {type(config).__name__}")
    return config


def _check_config(config_path: Path, config: dict[str, Any]) -> list[Path]:
    """``config``'s endpoints (``_check_endpoints``), then its files; returns the files."""
    _check_endpoints(config_path, config)
    return _check_files(config_path, config)


def _check_endpoints(config_path: Path, config: dict[str, Any]) -> None:
    """The shape of each endpoint the file lists (``endpoint_problem``), as ``--listen``/``--connect`` are checked:
    unchecked, Zenoh dials a port such as 99999 (and says nothing listens there) and a connect endpoint with no
    port never (the command waits its whole ``--timeout``). A list of endpoints per mode is checked whole. What
    is not a string is left to Zenoh to refuse."""
    for section in ("listen", "connect"):
        key = f"{section}/endpoints"
        value = lookup_key(config, key)
        for mode, endpoints in value.items() if isinstance(value, dict) else [(None, value)]:
            for endpoint in endpoints if isinstance(endpoints, list) else []:
                if isinstance(endpoint, str) and (problem := endpoint_problem(endpoint)):
                    raise SecureConfigError(f"{config_path}: {key}{'' if mode is None else f'/{mode}'}: {problem}")


def _check_files(config_path: Path, config: dict[str, Any]) -> list[Path]:
    checked = [_check_file(config_path, key, value) for key in FILE_KEYS
               if (value := lookup_key(config, key)) is not None]
    if any(lookup_key(config, key) for key in FILE_KEYS if "/tls/" in key):  # (cryptography: ~8 MiB, only then)
        from orchestrator import tlscheck
        tlscheck.check(config_path, config)
    return list(dict.fromkeys(checked))  # a file named twice (listen and connect TLS) is one file


@dataclass(frozen=True)
class Response:
    """One successful reply: its payload and optional attachment."""

    payload: bytes
    attachment: bytes | None = None


@dataclass(frozen=True)
class Incoming:
    """One query as a handler sees it: concrete key, payload, attachment."""

    key: str
    payload: bytes
    attachment: bytes | None


def _parse_error(payload: bytes) -> tuple[str, str]:
    try:
        body = json.loads(payload)
    except (json.JSONDecodeError, UnicodeDecodeError):
        return "remote", payload.decode("utf-8", "replace")
    if isinstance(body, dict) and isinstance(body.get("error"), dict):
        body = body["error"]
    if isinstance(body, dict):
        return str(body.get("error", body.get("code", "remote"))), str(body.get("message", body))
    return "remote", str(body)


def default_error_body(code: str, message: str) -> bytes:
    """The body :class:`Server` answers with when a handler crashes or a key is a pattern: the same shape as
    ``orchestrator.protocol.error_reply`` (this module may not import it)."""
    return json.dumps({"v": 1, "ok": False, "error": code, "message": message}).encode()


# --------------------------------------------------------------------------- config

#: Zenoh's cap on one reassembled message (bytes), checked by the receiver.
RX_MAX_MESSAGE_SIZE_KEY = "transport/link/rx/max_message_size"
#: Our value for it: the largest legitimate message is an episode upload, ``MAX_UPLOAD_BYTES`` (64 MiB,
#: ``orchestrator.protocol``, which this leaf may not import) of MCAP plus an attachment of at most
#: ``MAX_MESSAGE_BYTES`` (256 KiB) and Zenoh's own framing; 1 MiB above the upload limit covers both. Zenoh's
#: default is 1 GiB, so without it a peer could make the service buffer a gigabyte before our handler ever
#: answers ``too_large``.
RX_MAX_MESSAGE_BYTES = 65 * 1024 * 1024


def cap_incoming(config: zenoh.Config, written: dict[str, Any] | None = None) -> None:
    """Cap one incoming message at ``RX_MAX_MESSAGE_BYTES``, unless ``written`` (the parsed config file
    ``config`` was loaded from) sets ``RX_MAX_MESSAGE_SIZE_KEY`` itself: the operator's choice stands."""
    if written is None or lookup_key(written, RX_MAX_MESSAGE_SIZE_KEY) is None:
        config.insert_json5(RX_MAX_MESSAGE_SIZE_KEY, str(RX_MAX_MESSAGE_BYTES))


#: How long one link's Zenoh handshake may take (in ms), and Zenoh's default for it.
OPEN_TIMEOUT_KEY = "transport/unicast/open_timeout"
DEFAULT_OPEN_TIMEOUT_S = 10.0


def cap_handshake(config: zenoh.Config, seconds: float, written: dict[str, Any] | None = None) -> None:
    """A link's handshake gives up after ``seconds`` (at most Zenoh's default), unless ``written`` (the parsed
    config file) sets ``OPEN_TIMEOUT_KEY`` itself. An endpoint that takes the connection and never speaks Zenoh
    (an HTTP port, a TLS link to a plain TCP listener) holds the handshake that long, and closing the session
    waits for it."""
    if written is None or lookup_key(written, OPEN_TIMEOUT_KEY) is None:
        config.insert_json5(OPEN_TIMEOUT_KEY, str(max(1, round(1000 * min(seconds, DEFAULT_OPEN_TIMEOUT_S)))))


def make_config(mode: str = "peer", listen: Sequence[str] = (), connect: Sequence[str] = (),
                config_file: str | Path | None = None, handshake_s: float | None = None) -> zenoh.Config:
    """Build a Zenoh config.

    With ``config_file`` the file (Zenoh's own JSON5 format: routers, TLS, user/password, ACL) is used as written;
    ``listen``/``connect`` only add endpoints to it and ``mode`` is ignored. Without it: ``mode`` (``peer`` or
    ``client``), exactly the given endpoints, multicast scouting off (one machine, explicit endpoints; nothing is
    discovered behind our back).

    Either way the largest message this process accepts is ``RX_MAX_MESSAGE_BYTES``
    (``transport/link/rx/max_message_size``), unless the file sets that key itself. Zenoh drops a bigger message
    while reassembling it, once it has buffered about the cap; the link stays up and nothing tells the sender, whose
    ``get`` ends at its timeout (:class:`NoReplyError` from :func:`request`). Same-host peers may hand a message
    over in shared memory, which is not reassembled and so not capped (Zenoh's implicit pool is 16 MiB).

    ``handshake_s``: how long a link's handshake may take (``cap_handshake``); None: Zenoh's default, 10 s.

    Raises ``SecureConfigError`` when a file the config names (CA, certificate, key, password dictionary) is missing
    or unreadable or a certificate TLS would refuse, ``TransportError`` for an unknown mode or a config file Zenoh
    refuses.
    """
    if config_file is not None:
        written = read_config(Path(config_file))
        _check_config(Path(config_file), written)  # a bad endpoint, a missing cert or key: one line, before Zenoh
        try:
            config = zenoh.Config.from_file(str(config_file))
        except (zenoh.ZError, OSError, ValueError) as exc:
            raise TransportError(f"cannot load Zenoh config {config_file}: {zenoh_error(exc)}") from exc
        cap_incoming(config, written)
        if handshake_s is not None:
            cap_handshake(config, handshake_s, written)
        _add_endpoints(config, "listen", listen)
        _add_endpoints(config, "connect", connect)
        return config
    if mode not in MODES:
        raise TransportError(f"mode must be one of {MODES}, found {mode!r}")
    if mode == "client" and not connect:
        raise TransportError("client mode needs at least one connect endpoint, found none")
    config = zenoh.Config()
    try:
        config.insert_json5("mode", json.dumps(mode))
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/gossip/enabled", "false")  # peers learn no endpoints from each other
        cap_incoming(config)
        if handshake_s is not None:
            cap_handshake(config, handshake_s)
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except zenoh.ZError as exc:
        raise TransportError(f"bad endpoint in listen={list(listen)} connect={list(connect)}: "
                             f"{zenoh_error(exc)}") from exc
    return config


def _add_endpoints(config: zenoh.Config, section: str, endpoints: Sequence[str]) -> None:
    """Adds ``endpoints`` to ``config``'s ``section`` ("listen" or "connect"), keeping those it has
    (also in the per-mode form); raises TransportError for one Zenoh refuses."""
    if not endpoints:
        return
    current = json.loads(config.get_json(f"{section}/endpoints") or "null")
    if isinstance(current, dict):  # per-mode form: {"router": [...], "peer": [...], ...}
        merged: list[str] | dict[str, list[str]] = {
            k: list(v or []) + list(endpoints) for k, v in current.items()}
    else:
        merged = list(current or []) + list(endpoints)
    try:
        config.insert_json5(f"{section}/endpoints", json.dumps(merged))
    except zenoh.ZError as exc:
        raise TransportError(f"bad {section} endpoint in {list(endpoints)}: {zenoh_error(exc)}") from exc


def open_session(mode: str = "peer", listen: Sequence[str] = (), connect: Sequence[str] = (),
                 config_file: str | Path | None = None, handshake_s: float | None = None,
                 require_link: bool = False) -> zenoh.Session:
    """Open a Zenoh session from :func:`make_config`'s arguments; it says when a router link goes and comes back.

    Raises ``TransportError`` when Zenoh cannot open it (port in use, bad endpoint). When a client reaches none of
    its routers, the message says why instead of Zenoh's "Unable to connect": nothing listens there, a certificate
    is refused, or the router took the connection and refused the login (``orchestrator.linkprobe``).

    A peer's session opens whether or not anything answers at its connect endpoints (Zenoh keeps dialling them).
    ``require_link`` (a command that asks once and exits): a peer that opened with no link, scouts for no others
    and finds nothing taking a TCP connection at any of its connect endpoints fails as a client would, at once,
    saying so, instead of waiting its whole timeout. Endpoints a TCP connection cannot try (quic/, udp/, a unix
    socket) are left to Zenoh: a peer with one of them waits as before.
    """
    config = make_config(mode, listen, connect, config_file, handshake_s)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        said = zenoh_error(exc)
        if said.startswith(_UNABLE_TO_CONNECT):
            said = _why_unreachable(config, config_file) or said
        raise TransportError(f"cannot open Zenoh session (listen={list(listen)}, "
                             f"connect={list(connect)}, config={config_file}): {said}") from exc
    if require_link and not session.info.links() and (said := _why_unlinked(config, handshake_s)):
        session.close()
        raise TransportError(f"cannot link to a Zenoh peer (listen={list(listen)}, connect={list(connect)}, "
                             f"config={config_file}): {said}")
    _say_router_links(session)
    return session


def unlinked(session: zenoh.Session, endpoints: Sequence[str]) -> dict[str, str]:
    """Those of ``endpoints`` (connect endpoints) that ``session`` has no link to now (a peer's session keeps
    dialling them), each with why (``linkprobe``: nothing listens there, ...).

    A link's far end is an address (``tcp/127.0.0.1:7447``): an endpoint's host is resolved to compare.
    """
    up = linked(session, endpoints)
    return {ep: linkprobe.unreachable([ep], who="a Zenoh peer or router") or "no Zenoh link came up there"
            for ep in endpoints if ep not in up}


def linked(session: zenoh.Session, endpoints: Sequence[str]) -> list[str]:
    """Those of ``endpoints`` (connect endpoints) that ``session`` has a link to now, in their order."""
    far_ends = {link.dst for link in session.info.links()}
    return [ep for ep in endpoints if far_ends & _locators(ep)]


def _locators(endpoint: str) -> set[str]:
    """The far ends a link to ``endpoint`` may show: the endpoint without its metadata, and its host resolved."""
    parts = split_endpoint(endpoint)
    if parts.port_number is None:
        return {parts.locator}
    try:
        infos = socket.getaddrinfo(parts.bare_host, parts.port_number, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return {parts.locator}
    return {parts.locator} | {f"{parts.proto}/{_bracketed(str(info[4][0]))}:{parts.port}" for info in infos}


def _bracketed(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _why_unlinked(config: zenoh.Config, handshake_s: float | None) -> str:
    """``linkprobe.unreachable`` of a peer ``config``'s connect endpoints; '' for a client (it fails at open) or a
    peer that scouts (it may find the others by multicast)."""
    def value(key: str) -> Any:
        return json.loads(config.get_json(key) or "null")

    mode = value("mode") or "peer"  # (Zenoh's default)
    if mode != "peer" or value("scouting/multicast/enabled") is not False:
        return ""
    endpoints = value("connect/endpoints") or []
    if isinstance(endpoints, dict):  # per-mode form
        endpoints = endpoints.get(mode) or []
    return linkprobe.unreachable(endpoints, handshake_s or linkprobe.CONNECT_TIMEOUT_S,
                                 "`activecollect serve` (or a Zenoh router)")


#: How Zenoh says that a client reached none of its connect endpoints, whatever the reason.
_UNABLE_TO_CONNECT = "Unable to connect to any of"


def _why_unreachable(config: zenoh.Config, config_file: str | Path | None) -> str:
    """``linkprobe.diagnose`` of ``config``'s connect endpoints, with its TLS files and usrpwd user."""
    def value(key: str) -> Any:
        return json.loads(config.get_json(key) or "null")

    endpoints = value("connect/endpoints") or []
    if isinstance(endpoints, dict):  # per-mode form
        endpoints = endpoints.get(value("mode") or "client") or []
    tls = value("transport/link/tls") or {}

    def path(key: str) -> Path | None:
        return Path(tls[key]).expanduser() if tls.get(key) else None
    client_tls = linkprobe.ClientTls(path("root_ca_certificate"), path("connect_certificate"),
                                     path("connect_private_key"), tls.get("verify_name_on_connect") is not False)
    return linkprobe.diagnose(endpoints, client_tls, value("transport/auth/usrpwd/user"),
                              None if config_file is None else str(config_file))


def _say_router_links(session: zenoh.Session) -> None:
    """Warns when the session's link to a Zenoh router goes, and when one is back: Zenoh reconnects by itself and
    says nothing, while every query meanwhile goes unanswered (and the service takes its workers for gone)."""
    lost: list[float] = []

    def on_event(event: zenoh.TransportEvent) -> None:
        if event.transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        if event.kind == zenoh.SampleKind.DELETE:
            lost.append(time.monotonic())
            log.warning("lost the link to Zenoh router %s; reconnecting", event.transport.zid)
        elif lost:
            log.warning("linked to Zenoh router %s again after %.1f s", event.transport.zid, time.monotonic() - lost[0])
            lost.clear()

    session.info.declare_transport_events_listener(on_event, history=False)  # (a callback's lives with the session)


# --------------------------------------------------------------------------- querying

def request(session: zenoh.Session, key: str, payload: bytes = b"", attachment: bytes | None = None,
            timeout: float = 5.0) -> Response:
    """Send one query and return the first reply.

    Waits up to ``timeout`` seconds in all. A query that reaches nobody is re-sent with a short backoff until the
    deadline (declarations propagate asynchronously); one that reaches a queryable is never re-sent.

    Raises ``NoReplyError`` when nobody answers in time, ``RemoteError`` when the answer is an error reply.
    """
    deadline = time.monotonic() + timeout
    backoff = 0.02
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise NoReplyError(f"no reply on {key} within {timeout:g} s (is the service running "
                               f"and reachable?)")
        replies = session.get(key, payload=payload, attachment=attachment, timeout=remaining,
                              consolidation=zenoh.ConsolidationMode.NONE)
        got_any = False
        for reply in replies:
            got_any = True
            if reply.ok is not None:
                att = reply.ok.attachment
                return Response(reply.ok.payload.to_bytes(), att.to_bytes() if att is not None else None)
            err = reply.err
            if str(err.encoding).startswith(ERROR_ENCODING):
                raise RemoteError(key, err.payload.to_bytes())
            raise NoReplyError(f"no reply on {key} within {timeout:g} s: "
                               f"{err.payload.to_bytes().decode('utf-8', 'replace')}")
        if got_any:  # only non-matching replies; treat like silence
            continue
        time.sleep(min(backoff, max(deadline - time.monotonic(), 0)))
        backoff = min(backoff * 2, 0.25)


def query(session: zenoh.Session, key: str, payload: bytes = b"", attachment: bytes | None = None,
          timeout: float = 5.0) -> bytes:
    """:func:`request` returning only the reply payload."""
    return request(session, key, payload, attachment, timeout).payload
