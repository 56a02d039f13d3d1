"""CLI: ``activecollect router`` and ``activecollect secure init|check``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orchestrator.cli.common import (Parser, UsageError, add_json_arg, config_error, directory_path, print_json,
                                     positive_int)
from orchestrator.protocol import one_line
from orchestrator.router import RouterConfig, RouterError, RouterStartError, run_router
from orchestrator.secure import (DEFAULT_NAMESPACE, DEFAULT_ROUTER_ENDPOINT, MAX_VALID_DAYS, SecureInitConfig,
                                 host_problem, init_secure, profile_settings, router_endpoint_host, tls_endpoint)
from orchestrator.endpoints import config_file, endpoint, with_ports_chosen
from orchestrator.transport import SecureConfigError, validate_secure_config


def register(sub) -> None:
    """Adds ``router`` and ``secure``."""
    p = sub.add_parser("router", help="run a Zenoh router that orchestrator, workers and operators connect to",
                       description="Run a Zenoh router (eclipse-zenoh in router mode) that the orchestrator, workers "
                                   "and operators of a site connect to as clients; --connect links it to another "
                                   "site's router. It prints 'activecollect router <zid> listening on <endpoints>' "
                                   "once it listens and runs until SIGTERM or SIGINT (exit 0). Exit 2 for a bad "
                                   "endpoint or config or a file the config names that cannot be read; exit 1 for "
                                   "an endpoint it cannot listen on (a port in use).")
    p.add_argument("--listen", action="append", default=[], metavar="EP", type=endpoint,
                   help="endpoint to listen on, e.g. tls/0.0.0.0:7447 (repeatable; replaces the config "
                        "file's; default tcp/127.0.0.1:7447 without --zenoh-config)")
    p.add_argument("--connect", action="append", default=[], metavar="EP", type=endpoint,
                   help="another site's router to link to (repeatable; replaces the config file's)")
    p.add_argument("--zenoh-config", type=config_file, metavar="FILE",
                   help="Zenoh JSON5 config, e.g. router.json5 from `secure init`")
    p.set_defaults(func=_router)

    s = sub.add_parser("secure", help="secure profile: mutual TLS, passwords, default-deny ACL")
    ssub = s.add_subparsers(dest="secure_command", metavar="ACTION", parser_class=Parser)
    ssub.required = True
    init = ssub.add_parser("init", help="write a CA, per-role certificates and passwords, and "
                                        "router/orchestrator/worker/operator Zenoh configs",
                           description="Write a secure profile into DIR: a private CA, a certificate and key per "
                                       "role, a password per role and a Zenoh config per role (router, orchestrator, "
                                       "worker, operator) with mutual TLS and a default-deny ACL. The CA's key is "
                                       "not kept: to add or rotate a credential run it again with --force, which "
                                       "replaces the whole profile (or, on any failure, leaves the old one), and copy "
                                       "the new files to every host. Exit 2 when DIR holds other files.")
    init.add_argument("directory", type=_profile_dir, metavar="DIR",
                      help="where to write the profile: a new or empty directory (made private, mode 0700: it "
                           "holds the keys), or one holding a profile to replace with --force")
    init.add_argument("--namespace", default=None,
                      help=f"key namespace the ACL protects (default {DEFAULT_NAMESPACE}; with --force, the "
                           "replaced profile's)")
    init.add_argument("--router-endpoint", type=_router_endpoint, default=None,
                      metavar="tls/HOST:PORT",
                      help=f"where clients reach the router (default {DEFAULT_ROUTER_ENDPOINT}; with --force, the "
                           "replaced profile's)")
    init.add_argument("--router-listen", type=_router_listen, metavar="tls/ADDR:PORT",
                      help="what the router binds, e.g. tls/0.0.0.0:7447 (default: --router-endpoint; with "
                           "--force, the replaced profile's)")
    init.add_argument("--host", action="append", type=_host, default=None, dest="hosts", metavar="NAME",
                      help="another DNS name or IP address of the router for its certificate (repeatable; with "
                           "--force, default the replaced profile's)")
    init.add_argument("--valid-days", type=_valid_days, default=825, metavar="DAYS",
                      help=f"certificate lifetime in days, at most {MAX_VALID_DAYS} (default 825)")
    init.add_argument("--force", action="store_true",
                      help="replace an existing profile in DIR whole (also where DIR is a mount point)")
    add_json_arg(init)
    init.set_defaults(func=_init)
    check = ssub.add_parser("check", help="check the files a Zenoh config names: readable, certificates in date, "
                                          "matching their keys, signed by the CA",
                            description="Check that every file a Zenoh config names (CA, certificate, key, password "
                                        "dictionary) exists and is readable, and that its certificates are within "
                                        "their dates, match their keys and are signed by the CA they name, as every "
                                        "process given --zenoh-config does before it starts. Exit 2 in one line "
                                        "naming the first one that is not.")
    check.add_argument("config", type=config_file, metavar="FILE",
                       help="a Zenoh JSON5 config, e.g. DIR/worker.json5 from `secure init`")
    add_json_arg(check)
    check.set_defaults(func=_check)


def _profile_dir(text: str) -> Path:
    """``secure init``'s DIR: a directory, or a path where one can be made (a file there is a usage error)."""
    return directory_path(text, "a directory for the profile")


def _host(text: str) -> str:
    """A ``--host``: a DNS name or an IP address, as a certificate names the router."""
    if problem := host_problem(text):
        raise argparse.ArgumentTypeError(problem)
    return text


def _router_endpoint(text: str) -> str:
    """A ``--router-endpoint``: tls/HOST:PORT that clients connect to."""
    try:
        router_endpoint_host(text)
    except SecureConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _router_listen(text: str) -> str:
    """A ``--router-listen``: the tls/ADDR:PORT the router binds."""
    try:
        tls_endpoint(text, "router listen endpoint")
    except SecureConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _valid_days(text: str) -> int:
    """A ``--valid-days``: 1..MAX_VALID_DAYS (past about 2.9 million days a certificate's date overflows)."""
    days = positive_int(text)
    if days > MAX_VALID_DAYS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_VALID_DAYS} days (a hundred years), found {days}")
    return days


def _router(args: argparse.Namespace) -> int:
    try:
        cfg = RouterConfig(listen=with_ports_chosen(tuple(args.listen)), connect=tuple(args.connect),
                           zenoh_config=args.zenoh_config)
        return run_router(cfg, out=sys.stdout)
    except RouterStartError as exc:  # not a usage error: as `serve`, a port in use exits 1
        print(f"activecollect router: {one_line(str(exc))}", file=sys.stderr)
        return 1
    except RouterError as exc:
        raise UsageError(str(exc)) from exc


def _init(args: argparse.Namespace) -> int:
    given = {"namespace": args.namespace, "router_endpoint": args.router_endpoint,
             "router_listen": args.router_listen, "extra_hosts": None if args.hosts is None else tuple(args.hosts)}
    settings = {"namespace": DEFAULT_NAMESPACE, "router_endpoint": DEFAULT_ROUTER_ENDPOINT, "router_listen": None,
                "extra_hosts": ()}
    # a rotation (--force) keeps what the profile was made for, its hosts' endpoint and the router's names,
    # for each flag not given: the defaults' profile (127.0.0.1) would fail on every host it is copied to
    replaced = profile_settings(args.directory) if args.force else {}
    kept = {k: v for k, v in replaced.items() if given[k] is None and v != settings[k]}
    if "router_listen" in kept and given["router_endpoint"] is not None:
        # a bind on the old endpoint's port, kept for a new port, would leave clients connecting where nothing listens
        try:
            old_port = tls_endpoint(replaced["router_endpoint"])[1]
            moved = tls_endpoint(kept["router_listen"])[1] == old_port != tls_endpoint(given["router_endpoint"])[1]
        except SecureConfigError:
            moved = False  # (the config's own check names it below)
        if moved:
            raise UsageError(f"the replaced profile's router listens on {kept['router_listen']}, the port of its "
                             f"old endpoint {replaced['router_endpoint']}, not of --router-endpoint "
                             f"{given['router_endpoint']}: give --router-listen too")
    if kept:
        flags = {"namespace": "--namespace", "router_endpoint": "--router-endpoint",
                 "router_listen": "--router-listen", "extra_hosts": "--host"}
        shown = [f"{flags[k]} {x}" for k, v in kept.items() for x in (v if isinstance(v, tuple) else (v,))]
        print(f"activecollect secure init: keeping the replaced profile's {' '.join(shown)}", file=sys.stderr)
    settings.update(kept)
    settings.update({k: v for k, v in given.items() if v is not None})
    try:
        cfg = SecureInitConfig(directory=args.directory, force=args.force, valid_days=args.valid_days, **settings)
        result = init_secure(cfg)
    except SecureConfigError as exc:
        raise config_error(exc, {"namespace": "--namespace"} if str(exc).startswith("namespace:") else {}) from exc
    if result.left_over is not None:
        print(f"activecollect secure init: warning: the replaced profile could not be deleted; it holds the old "
              f"keys: delete {result.left_over}", file=sys.stderr)
    if args.json:
        print_json({"directory": str(result.directory), "ca_certificate": str(result.ca_certificate),
                    "configs": {role: str(p) for role, p in result.configs.items()},
                    "left_over": None if result.left_over is None else str(result.left_over)})
        return 0
    listen = f", listening on {cfg.router_listen}" if cfg.router_listen not in (None, cfg.router_endpoint) else ""
    print(f"wrote a secure profile to {result.directory} (namespace {cfg.namespace}, clients connect to the router "
          f"at {cfg.router_endpoint}{listen})")
    for role, path in result.configs.items():
        print(f"  {role:<12} {path}")
    print("start the router:  activecollect router --zenoh-config "
          f"{result.configs['router']}")
    print("copy to each host: ca.pem, ROLE.json5, ROLE.pem, ROLE-key.pem (same paths, or edit them)")
    return 0


def _check(args: argparse.Namespace) -> int:
    try:
        files = validate_secure_config(args.config)
    except SecureConfigError as exc:
        raise UsageError(str(exc)) from exc
    if args.json:
        print_json({"config": str(args.config), "files": [str(path) for path in files]})
        return 0
    print(f"{args.config}: {len(files)} referenced file(s) present and readable; certificates within their dates, "
          "matching their keys and signed by the CA named")
    for path in files:
        print(f"  {path}")
    return 0
