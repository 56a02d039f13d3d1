"""``activecollect router``: the real Zenoh router (the Rust core in eclipse-zenoh), not a relay of ours.

Orchestrator, workers and operators connect to it as clients; routers of other
sites connect to it with ``--connect``. In the secure profile its config file
(``secure init`` writes ``router.json5``) carries TLS, passwords and the ACL;
this module only opens the session, reports where it listens and waits for a
signal.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

import zenoh

from orchestrator.endpoints import keyless_tls_listener
from orchestrator.locators import endpoint_problem
from orchestrator.secure import is_secure_profile
from orchestrator.signals import on_stop_signals
from orchestrator.transport import SecureConfigError, cap_incoming, read_config, validate_secure_config, zenoh_error

#: Where a router listens when given neither --listen nor a config: loopback only, so an
#: unconfigured router is never reachable (in plaintext) from other hosts.
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


class RouterError(Exception):
    """The router cannot start: bad endpoint, unusable config, port in use. One line."""


class RouterStartError(RouterError):
    """Zenoh cannot open the router's session from a sound config: a port in use, an address not on this host."""


@dataclass
class RouterConfig:
    """What ``activecollect router`` runs."""

    listen: tuple[str, ...] = ()
    """Endpoints to listen on (proto/HOST:PORT); given, they replace zenoh_config's (so one profile
    serves several routers)."""
    connect: tuple[str, ...] = ()
    """Other routers to link to (one router per site, linked to each other); given, they replace
    zenoh_config's."""
    zenoh_config: Path | None = None
    """Zenoh JSON5 config passed through unchanged (the secure profile's router.json5)."""

    def __post_init__(self) -> None:
        self.listen, self.connect = tuple(self.listen), tuple(self.connect)
        for ep in (*self.listen, *self.connect):
            if problem := endpoint_problem(ep):
                raise RouterError(problem)
        if problem := keyless_tls_listener(self.listen, self.zenoh_config):
            raise RouterError(problem)
        if self.zenoh_config is not None:
            self.zenoh_config = Path(self.zenoh_config)


def build_router_config(cfg: RouterConfig) -> zenoh.Config:
    """The zenoh.Config of the router: the file (checked first) plus the extra endpoints.

    Raises RouterError for a missing/unreadable referenced file, a plaintext endpoint added
    to a TLS-only (secure) profile, or a config Zenoh refuses.
    """
    secure = False
    if cfg.zenoh_config is not None:
        try:
            validate_secure_config(cfg.zenoh_config)
            secure = is_secure_profile(cfg.zenoh_config)
            config = zenoh.Config.from_file(str(cfg.zenoh_config))
            cap_incoming(config, read_config(Path(cfg.zenoh_config)))  # a router relays only what it took in whole
        except SecureConfigError as exc:
            raise RouterError(str(exc)) from exc
        except zenoh.ZError as exc:
            raise RouterError(f"Zenoh refuses {cfg.zenoh_config}: {zenoh_error(exc)}") from exc
    else:
        config = zenoh.Config()
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("scouting/gossip/enabled", "false")
        cap_incoming(config)
    plain = [ep for ep in (*cfg.listen, *cfg.connect) if not ep.startswith(("tls/", "quic/"))]
    if secure and plain:
        raise RouterError(f"{cfg.zenoh_config} is a TLS-only profile; refusing plaintext endpoint {plain[0]}")
    try:
        config.insert_json5("mode", json.dumps("router"))
        # Given endpoints replace the file's (one profile serves several routers); without a file they
        # are exactly ours (Zenoh's own default listens on every interface).
        listen = cfg.listen or (() if cfg.zenoh_config is not None else (DEFAULT_LISTEN,))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if cfg.connect:
            config.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    except zenoh.ZError as exc:
        raise RouterError(f"Zenoh refuses the endpoints: {zenoh_error(exc)}") from exc
    return config


def listen_endpoints(config: zenoh.Config) -> list[str]:
    """The router-mode listen endpoints a config asks for."""
    value = json.loads(config.get_json("listen/endpoints"))
    if isinstance(value, dict):  # per-mode form {router: [...], peer: [...]}
        value = value.get("router", [])
    return list(value or [])


class Router:
    """One Zenoh router session. ``start()`` opens it (raises RouterStartError), ``stop()`` closes it."""

    def __init__(self, cfg: RouterConfig) -> None:
        self.cfg = cfg
        self.config = build_router_config(cfg)
        self.endpoints = listen_endpoints(self.config)
        self.session: zenoh.Session | None = None

    def start(self) -> None:
        try:
            self.session = zenoh.open(self.config)
        except zenoh.ZError as exc:
            raise RouterStartError(f"cannot start the router on {', '.join(self.endpoints) or '(none)'}: "
                              f"{zenoh_error(exc)}") from exc

    @property
    def zid(self) -> str:
        if self.session is None:
            raise RouterError("expected a started router, found none")
        return str(self.session.info.zid())

    def stop(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


def run_router(cfg: RouterConfig, out: TextIO, stop: threading.Event | None = None,
               on_ready: Callable[[Router], None] | None = None) -> int:
    """Runs a router until ``stop`` is set or SIGTERM/SIGINT arrives (main thread only; a SIGINT this process
    was started ignoring stays ignored: ``orchestrator.signals``); returns 0.

    Prints one ready line with its id and endpoints once the router is listening.
    """
    stop = stop or threading.Event()
    router = Router(cfg)
    restore = on_stop_signals(stop.set)
    try:
        router.start()
        where = " ".join(router.endpoints) or "(no endpoint: links only through --connect)"
        out.write(f"activecollect router {router.zid} listening on {where}\n")
        out.flush()
        if on_ready is not None:
            on_ready(router)
        while not stop.wait(0.5):
            pass
    finally:
        router.stop()
        restore()
    return 0
