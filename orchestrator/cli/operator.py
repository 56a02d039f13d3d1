"""The operator commands that talk to a running service: ``queue``, ``workers``, ``stats``, ``watch``.

Each is a Zenoh query to ``NS/admin/**`` (``orchestrator.admin`` answers it); when no service answers
they say so in one line and exit 1. (``serve`` and ``worker`` are in ``orchestrator.cli.service``.)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from orchestrator import acl, admin, endpoints, protocol, transport
from orchestrator.cli import common
from orchestrator.messages import AdminRequest, Event, RequestSpec
from orchestrator.protocol import Keys, ProtocolError
from orchestrator.uniform import uniform_start_state
from storage.requests import RequestStatus
from workers.policies import check_policy_params, policy_params_help


def register(sub: argparse._SubParsersAction) -> None:
    """Adds queue, workers, stats and watch."""
    _register_queue(sub)
    p = sub.add_parser("workers", help="workers known to the service")
    wsub = p.add_subparsers(dest="workers_command", metavar="CMD", parser_class=common.Parser)
    wsub.required = True
    p = wsub.add_parser("ls", help="workers alive and the leases they hold")
    _operator_args(p)
    p.set_defaults(func=cmd_workers_ls)
    p = sub.add_parser("stats", help="queue counts, episodes, champion, workers, free disk",
                       description="What a running service holds: requests by status, episodes by split and how "
                                   "many are quarantined, the champion and whether its weights can be served, "
                                   "live workers, and the free space on the data directory's disk.")
    _operator_args(p)
    p.set_defaults(func=cmd_stats)
    p = sub.add_parser("watch", help="follow the service's events (Ctrl-C to stop)",
                       description="Print the service's events as they happen (requests queued, leased, done or "
                                   "failed, episodes stored or rejected, models promoted, workers joining and lost), "
                                   "until Ctrl-C or --count events. Checks first that a service answers; when it "
                                   "goes away (stopped, restarting, cut off) says so on stderr and goes on watching, "
                                   "and says so again when one answers.")
    _operator_args(p)
    p.add_argument("--count", type=common.positive_int, default=None, metavar="N", help="exit after N events")
    p.set_defaults(func=cmd_watch)


def _register_queue(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("queue", help="the collection request queue of a running service")
    qsub = q.add_subparsers(dest="queue_command", metavar="CMD", parser_class=common.Parser)
    qsub.required = True
    p = qsub.add_parser("ls", help="requests, newest change first (--status queued: in lease order)")
    _operator_args(p)
    p.add_argument("--status", choices=[s.value for s in RequestStatus], default=None,
                   help="only requests in this state (default: all)")
    p.add_argument("--limit", type=_list_limit, default=50, metavar="N",
                   help=f"most requests to list, at most {admin.MAX_LIST} (default 50)")
    p.set_defaults(func=cmd_queue_ls)
    p = qsub.add_parser("show", help="one request in full")
    _operator_args(p)
    p.add_argument("id", type=_request_id, metavar="ID", help="a request id, or a unique prefix of one")
    p.set_defaults(func=lambda a: _print_op(a, "queue.show", {"id": a.id}, _print_request))
    p = qsub.add_parser("add", help="queue a manual request (a uniform start state unless --start-state)",
                        description="Queue a manual collection request: the next free worker that can collect "
                                    "--shape records it. A bad --start-state exits 2 (checked as the service "
                                    "checks any request); the service's refusal of it exits 1.")
    _operator_args(p)
    p.add_argument("--shape", required=True, choices=protocol.SHAPES, help="the object to push (required)")
    p.add_argument("--task", default="push", choices=protocol.TASKS, help="the task (default push)")
    p.add_argument("--policy", default="push", choices=protocol.POLICIES,
                   help="the scripted policy the worker runs (default push)")
    p.add_argument("--policy-params", type=_json_object, default={}, metavar="JSON",
                   help="the policy's parameters as a JSON object, e.g. '{\"side\": \"left\"}'; each policy's, "
                        f"with its defaults: {policy_params_help()}; push's side is left, right, top or bottom "
                        "(null: drawn) (default: the policy's defaults)")
    p.add_argument("--start-state", type=_json_object, default=None, metavar="JSON",
                   help="start state as a JSON object: shape (as --shape), agent [x, y] (the pusher), object "
                        f"[x, y, angle in radians], positions in 0..{protocol.WORLD_SIZE:g}; optional agent_vel "
                        "[vx, vy], object_vel [vx, vy, omega] (default at rest) and physics {mass, friction, "
                        "ground_friction} (default the defaults). E.g. '{\"shape\": \"T\", \"agent\": [100, 100], "
                        "\"object\": [256, 256, 0]}' (default: drawn uniformly with --seed)")
    p.add_argument("--seed", type=common.non_negative_int, default=None, metavar="K",
                   help="seed of the uniform start state, so not with --start-state (default: drawn from "
                        "--idempotency-key when given, so a retried add asks for the same start state; else random)")
    p.add_argument("--steps", type=common.episode_steps, default=50, metavar="T",
                   help=f"steps to record, {common.MIN_EPISODE_STEPS}..{common.MAX_EPISODE_STEPS} (default 50)")
    p.add_argument("--priority", type=_priority, default=0.0, metavar="P",
                   help=f"higher is leased first, within ±{protocol.MAX_PRIORITY:g} (default 0; planned requests "
                        "carry their score)")
    p.add_argument("--max-attempts", type=_max_attempts, default=3, metavar="N",
                   help=f"leases that may fail or expire before the request is dead, at most "
                        f"{protocol.MAX_ATTEMPTS} (default 3)")
    p.add_argument("--idempotency-key", default=None, metavar="KEY",
                   help="a repeated add with the same key returns the first request instead of a new one; "
                        "one that asks for something else (another shape, start state, policy, steps...) is "
                        "refused")
    p.set_defaults(func=cmd_queue_add)
    for name, op, help_text in (("cancel", "queue.cancel", "cancel a queued or leased request"),
                                ("retry", "queue.retry", "put a dead or cancelled request back in the queue")):
        p = qsub.add_parser(name, help=help_text)
        _operator_args(p)
        p.add_argument("id", type=_request_id, metavar="ID", help="a request id, or a unique prefix of one")
        p.set_defaults(func=lambda a, op=op: _print_op(a, op, {"id": a.id}, _print_request))
    p = qsub.add_parser("prioritize", help="set a request's priority (higher is leased first)")
    _operator_args(p)
    p.add_argument("id", type=_request_id, metavar="ID", help="a request id, or a unique prefix of one")
    p.add_argument("priority", type=_priority, metavar="PRIORITY",
                   help=f"the new priority, a number within ±{protocol.MAX_PRIORITY:g}; higher is leased first "
                        "(manual requests start at 0, planned ones at their score)")
    p.set_defaults(func=lambda a: _print_op(a, "queue.prioritize", {"id": a.id, "priority": a.priority},
                                            _print_request))


#: Every operator command's --help ends with this.
OPERATOR_EPILOG = ("Asks a running `activecollect serve` over Zenoh; exit 1 in one line when none answers within "
                   "--timeout (at once when nothing listens at any --connect endpoint), or when it refuses.")


def _operator_args(p: argparse.ArgumentParser) -> None:
    endpoints.add_connection_args(p)
    common.add_json_arg(p)
    p.epilog = OPERATOR_EPILOG


def _request_id(text: str) -> str:
    """An ID argument, checked as the service checks it (a usage error here, with or without a service)."""
    try:
        return protocol.check_id("ID", text)
    except ProtocolError as exc:
        raise argparse.ArgumentTypeError(exc.message.removeprefix("ID: ")) from None


def _priority(text: str) -> float:
    value = common.finite_float(text)
    if abs(value) > protocol.MAX_PRIORITY:
        raise argparse.ArgumentTypeError(f"expected a number within ±{protocol.MAX_PRIORITY:g}, found {text!r}")
    return value


def _positive_int_at_most(limit: int) -> Callable[[str], int]:
    """An argparse type: a positive integer no larger than ``limit`` (what the service accepts)."""
    def check(text: str) -> int:
        value = common.positive_int(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"expected at most {limit}, found {value}")
        return value
    return check


_max_attempts = _positive_int_at_most(protocol.MAX_ATTEMPTS)
_list_limit = _positive_int_at_most(admin.MAX_LIST)


def _no_constant(name: str) -> None:
    raise ValueError(f"{name} is not a JSON number")


def _finite(literal: str) -> float:
    """A JSON number literal as a float; one past float's range (``1e999``: inf) is refused, as the wire is."""
    value = float(literal)
    if not math.isfinite(value):
        raise ValueError(f"{literal} is out of range for a number")
    return value


def _json_object(text: str) -> dict:
    try:
        value = json.loads(text, parse_constant=_no_constant, parse_float=_finite)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a JSON object, found {text!r:.60} ({exc})") from None
    except RecursionError:
        raise argparse.ArgumentTypeError(f"expected a JSON object, found {text!r:.60} (nested too deeply)") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, found {type(value).__name__}")
    return value


# --- operator commands -----------------------------------------------------------------------------

class _NoService(Exception):
    """Nobody answered: printed as one line, exit 1."""


@contextmanager
def _session(args: argparse.Namespace) -> Iterator[zenoh.Session]:
    listen, connect = endpoints.endpoints_from_args(args)
    try:
        # (a link's handshake that outlasts --timeout cannot bring the reply in time: closing waits for it)
        session = transport.open_session(args.mode, listen, connect, args.zenoh_config, handshake_s=args.timeout,
                                         require_link=True)
    except transport.TransportError as exc:
        raise _NoService(str(exc)) from None
    try:
        yield session
    finally:
        session.close()


def admin_call(session: zenoh.Session, keys: Keys, op: str, args: dict[str, Any], timeout: float,
               zenoh_config: str | Path | None = None) -> dict[str, Any]:
    """One admin op over Zenoh; the reply body. Raises _NoService (``_no_answer`` says why), ProtocolError
    (refused).

    ``zenoh_config``: the session's config file, read again only when no answer comes: under a secure profile the
    router drops a query its ACL denies without a word, so a config of a role that may not make it is named.
    """
    try:
        reply = transport.query(session, keys.admin(op), AdminRequest(op=op, args=args).to_json(), timeout=timeout)
    except transport.NoReplyError:
        raise _NoService(_no_answer(keys, op, timeout, zenoh_config)) from None
    except transport.RemoteError as exc:
        raise ProtocolError(protocol.ErrorCode.INTERNAL, str(exc)) from None
    return protocol.parse_reply(reply)


def _no_answer(keys: Keys, op: str, timeout: float, zenoh_config: str | Path | None) -> str:
    """One line for an admin query nobody answered: no service, or (a secure profile's config) a role whose
    queries there the router's ACL drops, said outright when the config is a role's that ``secure init`` wrote."""
    said = f"no orchestrator answered on {keys.admin(op)} within {timeout:g} s"
    running = "is `activecollect serve` running and reachable?"
    if zenoh_config is None:
        return f"{said} ({running})"
    try:
        config = transport.read_config(Path(zenoh_config))
    except transport.SecureConfigError as exc:  # read at start a moment ago; gone since: no more to tell
        return f"{said} ({running}; {exc})"
    if denied := acl.denied_by_acl(config, Path(zenoh_config), keys.admin(op), keys.namespace, "admin queries"):
        return f"{said}, and none will: {denied}"
    if acl.client_role(config) is None and any(transport.lookup_key(config, key) for key in transport.FILE_KEYS):
        return (f"{said} ({running[:-1]} or your role may not be allowed this operation: the router's ACL drops a "
                f"denied request unanswered)")
    return f"{said} ({running})"


def namespace_keys(args: argparse.Namespace) -> Keys:
    """The keys of ``--namespace``; a usage error naming the flag when it is not a namespace."""
    try:
        return Keys(args.namespace)
    except ProtocolError as exc:
        raise common.UsageError(f"--{exc.message}" if exc.message.startswith("namespace:") else exc.message) from None


def _run_op(args: argparse.Namespace, op: str, op_args: dict[str, Any]) -> dict[str, Any]:
    keys = namespace_keys(args)
    with _session(args) as session:
        return admin_call(session, keys, op, op_args, args.timeout, args.zenoh_config)


def _failed(exc: Exception, op: str) -> int:
    """One line on stderr for a service that did not answer or refused ``op``; the exit status 1."""
    if isinstance(exc, ProtocolError):
        print(f"activecollect: {op} refused: {exc.code.value}: {exc.message}", file=sys.stderr)
    else:
        print(f"activecollect: {exc}", file=sys.stderr)
    return 1


def _print_op(args: argparse.Namespace, op: str, op_args: dict[str, Any], show) -> int:
    try:
        body = _run_op(args, op, op_args)
    except (_NoService, ProtocolError) as exc:
        return _failed(exc, op)
    if args.json:
        common.print_json(body)
    else:
        show(body)
    return 0


def _fmt_time(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def _print_request(body: dict[str, Any]) -> None:
    r = body["request"]
    created = body.get("created")
    if created is not None:
        print("queued" if created else "already queued (same idempotency key)")
    for k in ("id", "status", "priority", "task", "shape", "policy", "steps", "attempts", "max_attempts",
              "worker_id", "token", "episode_id", "last_error", "idempotency_key"):
        if k in r:
            value = r[k]
            shown = "-" if value is None else format(value, "g") if k == "priority" else value
            print(f"{k:>16}: {shown}")
    for k in ("created", "updated", "lease_expires"):
        if k in r:
            print(f"{k:>16}: {_fmt_time(r[k])}")
    for k in ("policy_params", "reason", "start_state"):
        if k in r:
            print(f"{k:>16}: {json.dumps(r[k], sort_keys=True)}")


def cmd_queue_ls(args: argparse.Namespace) -> int:
    def show(body: dict[str, Any]) -> None:
        print(" ".join(f"{k}={v}" for k, v in body["counts"].items()))
        print(f"{'ID':32}  {'STATUS':9} {'PRIO':>7} {'SHAPE':5} {'POLICY':16} {'FAILS':>5} {'WORKER':16} UPDATED")
        for r in body["requests"]:
            tries = f"{r['attempts']}/{r['max_attempts']}"
            print(f"{r['id']:32}  {r['status']:9} {r['priority']:7.3g} {r['shape']:5} {r['policy']:16} "
                  f"{tries:>5} {(r['worker_id'] or '-')[:16]:16} {_fmt_time(r['updated'])}")
        shown, total = len(body["requests"]), body.get("total")  # total: absent from older services
        if body.get("truncated"):
            print(f"list cut at {shown} of {total} requests to fit in one reply: narrow it with --status; "
                  "`queue show ID` shows one in full")
        elif total is not None and shown < total:
            print(f"{shown} of {total} requests (--limit N shows up to {admin.MAX_LIST})")
    op_args: dict[str, Any] = {"limit": args.limit}
    if args.status:
        op_args["status"] = args.status
    return _print_op(args, "queue.ls", op_args, show)


def _start_seed(seed: int | None, idempotency_key: str | None) -> int | None:
    """The uniform start state's seed: --seed, else one drawn from the idempotency key (so the same command,
    retried, asks for the same start state), else None (random)."""
    if seed is not None or idempotency_key is None:
        return seed
    return int.from_bytes(hashlib.sha256(idempotency_key.encode()).digest()[:8], "big")


def cmd_queue_add(args: argparse.Namespace) -> int:
    try:
        check_policy_params(args.policy, args.policy_params)
    except ValueError as exc:
        raise common.UsageError(f"--policy-params: {exc}") from None
    if args.start_state is not None and args.seed is not None:
        raise common.UsageError("--seed draws the uniform start state: it does not apply with --start-state")
    start = args.start_state
    if start is None:
        start = uniform_start_state(np.random.default_rng(_start_seed(args.seed, args.idempotency_key)), args.shape)
    op_args = {"task": args.task, "shape": args.shape, "start_state": start, "policy": args.policy,
               "policy_params": args.policy_params, "steps": args.steps, "priority": args.priority,
               "max_attempts": args.max_attempts}
    if args.idempotency_key is not None:
        op_args["idempotency_key"] = args.idempotency_key
    try:  # the service's own check of the request, here: a bad --start-state is the caller's usage error
        RequestSpec.from_dict(op_args)
    except ProtocolError as exc:
        if args.start_state is None:  # (then only the key can be wrong: the other fields are argparse's)
            raise common.config_error(ValueError(exc.message), {"idempotency_key": "--idempotency-key"}) from None
        raise common.UsageError(f"--start-state: {exc.message}") from None
    def show(body: dict[str, Any]) -> None:
        _print_request(body)
        held = body["request"]["priority"]
        if not body.get("created") and held != args.priority:  # (a repeat changes nothing: priority is no ask)
            print(f"its priority stays {held:g}, not --priority {args.priority:g}: `queue prioritize "
                  f"{body['request']['id']} {args.priority:g}` sets it")
    return _print_op(args, "queue.add", op_args, show)


def cmd_workers_ls(args: argparse.Namespace) -> int:
    def show(body: dict[str, Any]) -> None:
        print(f"{'WORKER':32} {'ALIVE':5} LEASES")
        for w in body["workers"]:
            print(f"{w['id']:32} {'yes' if w['alive'] else 'no':5} {' '.join(w['leases']) or '-'}")
        if body.get("truncated"):  # (absent from older services)
            print(f"list cut at {len(body['workers'])} of {body['total']} workers to fit in one reply: those "
                  "holding leases first, then the others by id; `queue ls --status leased` lists the leases")
    return _print_op(args, "workers.ls", {}, show)


def cmd_stats(args: argparse.Namespace) -> int:
    def show(body: dict[str, Any]) -> None:
        print("requests: " + " ".join(f"{k}={v}" for k, v in body["requests"].items()))
        episodes, held = body.get("episodes") or {}, body.get("quarantine_bytes")  # (absent from older services)
        print("episodes: " + (" ".join(f"{k}={v}" for k, v in episodes.items()) or "-")
              + (f" (their files take {held / 1e6:.1f} MB in DATA/quarantine/)" if held else ""))
        problem, h1 = body.get("champion_problem"), body.get("champion_h1_mse")  # (h1: absent from older services)
        print(f"champion: {body.get('champion') or '-'}" + (f" (h1 MSE {h1:.3g})" if isinstance(h1, float) else "")
              + (f" (CANNOT BE SERVED: {problem})" if problem else ""))
        print(f"workers:  {body.get('workers', 0)} alive")
        print(f"disk:     {disk_line(body.get('disk'))}")
    return _print_op(args, "stats", {}, show)


def disk_line(disk: dict[str, int] | None) -> str:
    """``12.3 GiB free of 50.0 GiB (25 %)`` for a ``storage.database.disk_json`` value; '-' when unknown."""
    if not disk or not disk.get("size_bytes"):
        return "-"
    free, size = disk["free_bytes"], disk["size_bytes"]
    return f"{free / 2**30:.1f} GiB free of {size / 2**30:.1f} GiB ({100 * free / size:.0f} %)"


def cmd_watch(args: argparse.Namespace) -> int:
    """Print events as they come; first checks that a service answers."""
    keys = namespace_keys(args)
    left = _Countdown(args.count)
    try:
        with _session(args) as session:
            admin_call(session, keys, "stats", {}, args.timeout, args.zenoh_config)
            sub = session.declare_subscriber(keys.events_all, lambda s: _print_event(s, args.json, left))
            querier, listener = _follow_service(session, keys)
            if not args.json:  # (on stderr, as the service's coming and going: stdout holds the events only)
                print(f"# watching {keys.events_all} (Ctrl-C to stop)", file=sys.stderr, flush=True)
            try:
                left.done.wait()
                if left.error is not None:  # (stdout closed: `watch | head`; main says so, as for any command)
                    raise left.error
            finally:
                listener.undeclare()
                querier.undeclare()
                sub.undeclare()
    except (_NoService, ProtocolError) as exc:
        return _failed(exc, "stats")
    return 0


def _follow_service(session: zenoh.Session, keys: Keys) -> tuple[zenoh.Querier, Any]:
    """A querier on the service's admin key and its matching listener, which says on stderr when no service
    serves it any more (stopped, restarting, cut off) and when one does again: from its events alone, a service
    that went away looks like a quiet one. Returns both, to undeclare."""
    key = keys.admin("stats")
    there = [True]  # watch follows once a service has answered

    def changed(status: Any) -> None:
        if status.matching == there[0]:  # the listener's first call says what is already known
            return
        there[0] = status.matching
        print(f"# a service answers on {key} again; its events follow" if status.matching else
              f"# no service answers on {key} any more (stopped, restarting or cut off); still watching",
              file=sys.stderr, flush=True)

    querier = session.declare_querier(key)
    return querier, querier.declare_matching_listener(changed)


class _Countdown:
    """The events ``watch`` has yet to print (``--count``; None: no end); ``done`` is set once it has printed them.
    Zenoh hands the subscriber events while the command ends too: those are not printed."""

    def __init__(self, count: int | None) -> None:
        self.left, self.lock, self.done = count, threading.Lock(), threading.Event()
        self.error: OSError | None = None
        """Why printing failed (a closed pipe): raised by the main thread, which ends the command; an error
        raised in Zenoh's callback thread would only be logged there, and watch would wait on for ever."""


def _print_event(sample: zenoh.Sample, as_json: bool, left: _Countdown) -> None:
    try:
        event = Event.from_json(sample.payload.to_bytes())
    except ProtocolError as exc:
        print(f"# unreadable event on {sample.key_expr}: {exc}", file=sys.stderr, flush=True)
        return
    if as_json:
        line = json.dumps(event.to_dict(), sort_keys=True)
    else:
        data = " ".join(f"{k}={v}" for k, v in sorted(event.data.items()))
        line = f"{_fmt_time(event.at)} {event.kind:20} {data}"
    with left.lock:  # (one event at a time: the N-th is printed before the command may end)
        if left.done.is_set():
            return
        try:
            print(line, flush=True)
        except OSError as exc:
            left.error = exc
            left.done.set()
            return
        if left.left is not None:
            left.left -= 1
            if left.left == 0:
                left.done.set()
