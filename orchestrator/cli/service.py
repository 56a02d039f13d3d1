"""``activecollect serve`` and ``worker``; the operator commands that talk to a running service are in
``orchestrator.cli.operator``.

Nothing here imports torch: ``serve``'s champion scorer loads it with the first champion.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from orchestrator import acl, dispatchbench, endpoints, transport
from orchestrator.champion import ChampionScorer
from orchestrator.cli import common
from orchestrator.cli.loop import add_retrain_args_arg
from orchestrator.cli.operator import namespace_keys
from orchestrator.companions import CompanionConfig, Companions, fitted_retrain_threads
from orchestrator.planner import ActivePlanner, ActivePlannerConfig, in_eval_split
from orchestrator.protocol import one_line
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from orchestrator.service import Service
from orchestrator.serviceconfig import (SECONDS_RANGES, PlannerFactory, ServiceConfig, ServiceContext, ServiceError,
                                        where_served)
from orchestrator.signals import Terminated, on_stop_signals, sigterm_raises
from storage.database import DB_NAME
from storage.errors import StorageError
from storage.requests import RequestStatus
from workers import cli as worker_cli

PLANNERS = ("active", "uniform", "none")
#: ``serve``'s torch threads for scoring (``ChampionScorer.threads``); its retrain jobs get the other cores.
SCORING_THREADS = 1
#: ``serve``'s queue floor: an idle worker of two finds work at once while the planner catches up.
MIN_QUEUED = 2
#: The planners ``serve`` builds stop adding requests once this many are queued (their configs' default).
QUEUE_DEPTH_CAP = min(UniformPlannerConfig.max_queue_depth, ActivePlannerConfig.max_queue_depth)
#: ``serve``'s seconds between looks for expired leases (at most its lease).
REAP_INTERVAL_S = 1.0


def register(sub: argparse._SubParsersAction) -> None:
    """Adds serve and worker."""
    p = sub.add_parser("serve", help="run the orchestrator: queue, leases, uploads, admin over Zenoh",
                       description="Run the orchestrator service over the data directory at --data: the request "
                                   "queue, leases, uploads and admin over Zenoh, the planner, the dashboard and "
                                   "scheduled retrains (each a `retrain` child process), until SIGTERM or Ctrl-C "
                                   "(exit 0). Exit 1 when it cannot start (an endpoint taken, an unusable data "
                                   "directory, one another serve or run holds: DATA/service.lock); exit 2 for bad "
                                   "flags, or a --data that holds no catalog without --init.")
    common.add_data_arg(p)
    p.add_argument("--init", action="store_true",
                   help="start a new data directory at --data when there is none (without it, a --data that "
                        "holds no catalog is refused: a misspelt path, or the data directory's parent, must not "
                        "start a new, empty catalog)")
    endpoints.add_connection_args(p, listen=True)
    p.add_argument("--lease-s", type=common.seconds_in(*SECONDS_RANGES["lease_s"]), default=30.0, metavar="S",
                   help="seconds a worker holds a request before it must renew the lease or lose it, 0.05..86400 "
                        "(default 30)")
    p.add_argument("--reap-interval-s", type=common.seconds_in(*SECONDS_RANGES["reap_interval_s"]), default=None,
                   metavar="S",
                   help=f"seconds between looks for expired leases, 0.01..3600 and at most --lease-s (default "
                        f"{REAP_INTERVAL_S:g}, or --lease-s when shorter)")
    p.add_argument("--lost-worker-grace", type=common.seconds_in(*SECONDS_RANGES["lost_worker_grace_s"]),
                   default=ServiceConfig.lost_worker_grace_s,
                   metavar="S", help="seconds a worker whose liveliness token went keeps its leases before they go "
                   "back to the queue, 0..86400 (default %(default)g; 0 = at once). When a Zenoh router restarts or "
                   "a link blips, every worker's token goes and comes back a few seconds later: within the grace "
                   "each keeps its lease and its episode is stored (a worker that is gone has its request queued "
                   "again that much later). A lease still expires after --lease-s without renewals")
    p.add_argument("--planner", choices=PLANNERS, default="active",
                   help="what turns stored episodes into requests (default active)")
    p.add_argument("--seed-requests", type=common.non_negative_int, default=0, metavar="N",
                   help="uniform requests to seed an empty queue with at start (default 0)")
    p.add_argument("--min-queued", type=common.non_negative_int, default=None, metavar="N",
                   help=f"with a planner, keep at least N requests queued: when its own requests run out, uniform "
                        f"draws top the queue up so collection never stops (at most the planner's queue depth "
                        f"cap, {QUEUE_DEPTH_CAP}; default {MIN_QUEUED}, 0 with --planner none; 0 = no floor)")
    p.add_argument("--steps", type=common.episode_steps, default=50, metavar="T",
                   help=f"steps per planned episode, {common.MIN_EPISODE_STEPS}..{common.MAX_EPISODE_STEPS} "
                        "(default 50)")
    p.add_argument("--seed", type=common.non_negative_int, default=0, metavar="K",
                   help="seed of the planner's generator (default 0)")
    p.add_argument("--scoring-threads", type=common.torch_threads, default=SCORING_THREADS, metavar="N",
                   help=f"torch threads the service scores episodes with (default {SCORING_THREADS}; 0 = torch's "
                        f"default, one per core)")
    p.add_argument("--retrain-threads", type=common.torch_threads, default=None, metavar="N",
                   help="torch threads of each retrain job (default: the cores the scoring leaves, here "
                        f"{fitted_retrain_threads(SCORING_THREADS)}; 0 = torch's default, one per core; a --threads "
                        "in --retrain-args wins). Two processes with more threads than cores between them slow "
                        "each other several times over while both are busy; on 2 cores, 0 retrains 1.17x "
                        "faster while the scoring is mostly idle (a small fleet; BENCHMARKS.md)")
    d = CompanionConfig()
    p.add_argument("--dashboard-port", type=common.dashboard_port, default=d.dashboard_port, metavar="PORT",
                   help=f"dashboard on 127.0.0.1:PORT (0 = any free port, -1 = none; default {d.dashboard_port})")
    common.add_dashboard_limit_args(p, prefix="dashboard-")
    p.add_argument("--retrain-every", type=common.non_negative_int, default=d.retrain_every, metavar="N",
                   help="retrain (in a child process) each time the number of training episodes reaches a "
                        "multiple of N (the 100th, 200th, ... for 100: the schedule holds across restarts; default 0 "
                        "= not on count)")
    p.add_argument("--retrain-cron", type=common.cron_expression, default=d.retrain_cron, metavar="EXPR",
                   help="also retrain on this cron expression of 5 fields (minute hour day month weekday), read in "
                        "UTC, e.g. '0 * * * *' or @hourly (default: not on time)")
    add_retrain_args_arg(p, d.retrain_args)
    p.add_argument("--retrain-timeout", type=common.seconds_in(1, 7 * 86400), default=d.retrain_timeout_s,
                   metavar="S", help="a retrain job running longer than S seconds is killed, changing nothing unless "
                   "its gate had decided (default %(default)g: 4 h). A job trains on every training window unless "
                   "--retrain-args bounds them with --max-windows, so its time grows with the catalog: on 2 CPU "
                   "cores retrain's defaults take ~90 ms a window (30 minutes at ~400 episodes of 50 steps)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="least severe log messages written to stderr (default INFO)")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("worker", help="run a collector worker: lease, simulate, record MCAP, upload",
                       description=worker_cli.DESCRIPTION)
    worker_cli.add_arguments(p)
    p.set_defaults(func=worker_cli.run_from_args)


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("dispatch", help="lease->complete round trips/s and latency vs raw Zenoh queries",
                             description="Lease round trips/s and latency of a service in a child process over "
                                         "loopback, with --workers concurrent clients, against raw Zenoh queries "
                                         "measured in the same run; then the queue alone and the upload path.")
    p.add_argument("--workers", type=_dispatch_clients, default=8, metavar="N",
                   help=f"concurrent dispatch clients, at most {dispatchbench.MAX_WORKERS} (default 8)")
    p.add_argument("--seconds", type=common.positive_float, default=5.0, metavar="S",
                   help="measuring time per phase in seconds (default 5)")
    p.add_argument("--data", type=common.data_dir, default=None, metavar="DIR",
                   help="a new or empty data directory, kept afterwards (default: a temporary one)")
    common.add_json_arg(p)
    p.set_defaults(func=cmd_bench_dispatch)


def _dispatch_clients(text: str) -> int:
    """``bench dispatch --workers``: 1..``dispatchbench.MAX_WORKERS`` (episodes are encoded per client up front)."""
    return common.int_in(text, 1, dispatchbench.MAX_WORKERS, "a positive integer",
                         "clients (the upload phase encodes 1500 episodes per client before it starts)")


# --- serve ---------------------------------------------------------------------------------------

def planner_factory(name: str, steps: int, seed: int, threads: int = 0) -> PlannerFactory | None:
    """The factory ``serve --planner`` names (None for ``none``); ``threads`` is the champion scorer's."""
    if name == "none":
        return None

    def build(ctx: ServiceContext):
        rng = np.random.default_rng(seed)
        depth = lambda: ctx.queue.counts()[RequestStatus.QUEUED.value]  # noqa: E731
        uniform = UniformPlannerConfig(steps=steps)
        if name == "uniform":
            return UniformPlanner(uniform, rng, depth)
        scorer = ChampionScorer(ctx.data_dir, observe=ctx.metrics.observe_scoring, threads=threads)
        planner = ActivePlanner(ActivePlannerConfig(steps=steps, seed_uniform=uniform), scorer, rng, depth,
                                is_eval=in_eval_split(ctx.catalog))
        planner.remember_queue(ctx.queue)
        return planner

    return build


def companion_config(args: argparse.Namespace) -> CompanionConfig:
    """``serve``'s dashboard and retrain schedule (a bad one is a usage error)."""
    try:
        return CompanionConfig(dashboard_port=args.dashboard_port, dashboard_max_connections=args.max_connections,
                               dashboard_request_timeout_s=args.request_timeout, retrain_every=args.retrain_every,
                               retrain_cron=args.retrain_cron, retrain_args=args.retrain_args,
                               retrain_threads=args.retrain_threads, scoring_threads=args.scoring_threads,
                               retrain_timeout_s=args.retrain_timeout)
    except ValueError as exc:
        raise common.config_error(exc) from None


def _min_queued(args: argparse.Namespace) -> int:
    """``--min-queued``, and ``--seed-requests``, checked against the planner that would have to draw them."""
    if args.seed_requests and args.planner == "none":  # (it used to queue nothing, silently)
        raise common.UsageError("--seed-requests needs a planner to draw requests from; with --planner none "
                                "nothing is seeded (use --planner uniform or active, or queue add)")
    if args.min_queued is None:
        return 0 if args.planner == "none" else MIN_QUEUED
    if args.min_queued and args.planner == "none":
        raise common.UsageError("--min-queued needs a planner to draw requests from; with --planner none "
                                "nothing tops the queue up (use --planner uniform or active)")
    if args.min_queued > QUEUE_DEPTH_CAP:
        raise common.UsageError(f"--min-queued {args.min_queued} is above the planner's queue depth cap of "
                                f"{QUEUE_DEPTH_CAP}: the floor could never be reached")
    return args.min_queued


def _reap_interval(args: argparse.Namespace) -> float:
    """``--reap-interval-s``, at most ``--lease-s``: a lease that ran out waits for the next look to go back to the
    queue, so a longer interval would keep a lost worker's request out of it for longer than the lease itself."""
    if args.reap_interval_s is None:
        return min(REAP_INTERVAL_S, args.lease_s)
    if args.reap_interval_s > args.lease_s:
        raise common.UsageError(f"--reap-interval-s {args.reap_interval_s:g} is longer than --lease-s "
                                f"{args.lease_s:g}: an expired lease would wait up to {args.reap_interval_s:g} s "
                                f"more to go back to the queue; give at most {args.lease_s:g}")
    return args.reap_interval_s


def cmd_serve(args: argparse.Namespace) -> int:
    min_queued = _min_queued(args)
    reap_interval_s = _reap_interval(args)
    keys = namespace_keys(args)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    listen, connect = endpoints.endpoints_from_args(args)
    listen = endpoints.with_ports_chosen(listen)  # (Zenoh would not say which port :0 got)
    if args.mode == "client" and not connect and args.zenoh_config is None:  # (Zenoh would refuse it at start)
        raise common.UsageError("--mode client needs --connect EP: a client listens on nothing and reaches the "
                                "others through a router (activecollect router)")
    written = transport.read_config(args.zenoh_config) if args.zenoh_config is not None else None
    if written is not None:  # another role's profile config: no request would ever reach this service
        if denied := acl.denied_by_acl(written, Path(args.zenoh_config), keys.lease,
                                       keys.namespace, "the declarations of the service's queryables",
                                       "declare_queryable"):
            raise common.UsageError(f"--zenoh-config: {denied}")
    extras = companion_config(args)
    try:
        config = ServiceConfig(data_dir=args.data, namespace=args.namespace, mode=args.mode, listen=listen,
                               connect=connect, zenoh_config=args.zenoh_config, lease_s=args.lease_s,
                               reap_interval_s=reap_interval_s, lost_worker_grace_s=args.lost_worker_grace,
                               seed_requests=args.seed_requests,
                               min_queued=min_queued,
                               planner=planner_factory(args.planner, args.steps, args.seed, args.scoring_threads))
    except ServiceError as exc:
        raise common.config_error(exc, {"namespace": "--namespace", "mode": "--mode"}) from None
    if not args.init and not (args.data / DB_NAME).is_file():  # (data_dir has refused a file there)
        # (a directory without a catalog too: the likeliest slip is its parent, /srv/ac for /srv/ac/data)
        raise common.UsageError(f"{'no catalog in' if args.data.is_dir() else 'no data directory at'} {args.data}: "
                                "give the directory a serve, run or collect made, or --init to start a new one there")
    stop = threading.Event()
    on_stop_signals(stop.set)  # (SIGINT stays ignored when serve was started ignoring it)
    service = Service(config)
    companions = Companions(extras, service)
    try:
        try:
            service.start()
            companions.start()
        except BaseException:  # whatever it is, nothing keeps running behind it
            companions.stop()
            service.stop()
            raise
    except (ServiceError, StorageError, ValueError, OSError) as exc:  # StorageError: the scheduler's count
        print(f"activecollect serve: {one_line(str(exc))}", file=sys.stderr)
        return 1
    if companions.dashboard is not None:
        print(f"dashboard at {companions.dashboard.url}", flush=True)
    if (args.retrain_every or args.retrain_cron) and _no_eval_split(service):  # (before "serving")
        logging.getLogger("orchestrator.service").warning(
            "no eval split is pinned in %s: every scheduled retrain fails until one is (activecollect eval-split "
            "create --data %s, or ingest --split eval and eval-split pin)", args.data, args.data)
    where = _reached(service, listen, connect, args.zenoh_config, _mode(args.mode, written))
    print(f"serving {args.namespace} {where} "
          f"(data {args.data}, planner {args.planner}); Ctrl-C to stop", flush=True)
    try:
        stop.wait()
    finally:
        companions.stop()
        service.stop()
    return 0


def _reached(service: Service, listen: tuple[str, ...], connect: tuple[str, ...], zenoh_config: Path | None,
             mode: str) -> str:
    """``where_served``, where a --connect endpoint the session has no link to is "dialling" (a peer's session
    opens without one and keeps trying), with a warning saying why. Only a peer's: a client links to one of its
    routers and dials none of the others while it has that link (and it opens with none only to fail); it is
    connected to that one, the others named as what it turns to if that link goes."""
    if mode == "client" and (up := transport.linked(service.session, connect)):
        others = [ep for ep in connect if ep not in up]
        where = where_served(listen, tuple(up), zenoh_config, linked=True)
        return where + (f" ({', '.join(others)} if that link goes)" if others else "")
    dialling = transport.unlinked(service.session, connect) if mode == "peer" else {}
    for ep, why in dialling.items():
        logging.getLogger("orchestrator.service").warning("no link to --connect %s yet (%s); Zenoh keeps dialling it",
                                                          ep, why)
    where = where_served(listen, tuple(ep for ep in connect if ep not in dialling), zenoh_config, linked=True)
    return ", ".join(filter(None, [where, f"dialling {', '.join(dialling)}" if dialling else ""]))


def _mode(given: str, written: dict[str, Any] | None) -> str:
    """The Zenoh mode serve runs in: ``given`` (--mode), or the mode of its --zenoh-config as ``written`` there (read
    once, before the session opened with it: a Zenoh session does not say its mode)."""
    return given if written is None else str(written.get("mode") or "peer")  # (Zenoh's default)


def _no_eval_split(service: Service) -> bool:
    """Whether the service's catalog has no eval split pinned (False when it cannot be read now: a retrain's own
    error will say what it finds)."""
    try:
        return service.catalog.eval_split() is None
    except StorageError:
        return False


# --- bench -------------------------------------------------------------------------------------

def cmd_bench_dispatch(args: argparse.Namespace) -> int:
    if args.data is not None and args.data.exists() and (not args.data.is_dir() or any(args.data.iterdir())):
        # a run leaves requests in its queues: the next one would lease them, with no episode made for them
        raise common.UsageError(f"--data {args.data} is not an empty directory; give a new or empty one")
    try:
        with sigterm_raises():  # a supervisor's stop unwinds as Ctrl-C does: servers stopped, temp dir gone
            result = dispatchbench.run(dispatchbench.BenchConfig(workers=args.workers, seconds=args.seconds,
                                                                 data_dir=args.data))
    except Terminated:
        print("activecollect: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    if args.json:
        common.print_json(result)
    else:
        print(dispatchbench.format_result(result))
    return 0
