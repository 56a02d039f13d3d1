"""The worker's command line, shared by ``activecollect worker`` and ``python -m workers.agent``.

``python -m workers.agent`` needs neither torch nor the service's code: a collector host installs only what
the simulator needs. Imports what ``workers.agent`` does.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path

from orchestrator import acl, endpoints, protocol, signals, transport
from storage.records import TRAINABLE_SIZES
from workers import flags, startup
from workers.startup import DRAIN_SIGNAL
from workers.agent import Worker, WorkerConfig, WorkerError
from workers.env import CONTROL_HZ
from workers.flags import MAX_REALTIME
from workers.upload import DEFAULT_PART_KB, MAX_PART_KB

log = logging.getLogger("workers.agent")

#: ``--help``'s description of ``activecollect worker`` and ``python -m workers.agent``.
DESCRIPTION = ("Run a collector worker: lease requests from the service over Zenoh, simulate and record each "
               "episode as MCAP at the frame size the lease names, upload it; until stopped (or --once, "
               "--max-episodes). SIGTERM / SIGINT drain it: it finishes and uploads the episode in hand, then "
               "exits (a second one drops that episode at once and gives the request back); SIGUSR1 drains and "
               "never escalates. Exit 0 when done or stopped (also when stopped while starting); 1 when it cannot "
               "start, when a second signal dropped an episode, or when a service that was there would not store "
               "an episode it collected while draining (the request goes back to the queue); 2 for bad flags.")


def parse_capabilities(text: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``"push:T,box"`` -> (("push",), ("T", "box")); ``"T,box"`` -> ((), ("T", "box")); ``"push:"`` -> push, any
    shape; ``""`` -> any.

    Raises WorkerError naming the unknown task or shape, or a non-empty text that names none (``":T"``, ``","``).
    """
    given = text.strip()
    if not given:
        return (), ()
    tasks: tuple[str, ...] = ()
    text = given
    if ":" in text:
        task_part, text = text.split(":", 1)
        tasks = tuple(t.strip() for t in task_part.split("+") if t.strip())
        if not tasks:  # (":T" or ":" would otherwise quietly mean any task)
            raise WorkerError(f"capabilities: expected a task before ':' (tasks in {protocol.TASKS}), found {given!r}")
    elif text in protocol.TASKS:
        return (text,), ()
    shapes = tuple(s.strip() for s in text.split(",") if s.strip())
    if not tasks and not shapes:  # ("," would otherwise quietly mean anything)
        raise WorkerError(f"capabilities: expected TASK:SHAPE,... with tasks in {protocol.TASKS} and shapes in "
                          f"{protocol.SHAPES}, found no task or shape in {given!r}")
    bad = [t for t in tasks if t not in protocol.TASKS] + [s for s in shapes if s not in protocol.SHAPES]
    if bad:
        raise WorkerError(f"capabilities: expected TASK:SHAPE,... with tasks in {protocol.TASKS} and shapes in "
                          f"{protocol.SHAPES}, found {', '.join(bad)}")
    return tasks, shapes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The worker's flags; errors are labelled with ``parser.prog`` (the program the user ran)."""
    endpoints.add_connection_args(parser, timeout=10.0)
    parser.add_argument("--id", default=None, help="worker id (default <host>-<pid>)")
    parser.add_argument("--capabilities", default=None, metavar="C",
                        help='what it can collect: "push:T,box", "T,box" or "push" (default: anything)')
    parser.add_argument("--once", action="store_true",
                        help="handle at most one request, then exit; exit at once when the service has no work "
                             "for this worker (a service that does not answer is waited for; one that refuses the "
                             "lease query, another release's, or whose reply cannot be read: exit 1)")
    parser.add_argument("--max-episodes", type=flags.positive_int, default=None, metavar="N",
                        help="exit after N uploads (default: run until stopped)")
    parser.add_argument("--size", type=flags.frame_size, default=64, metavar="PX",
                        help="frame side in pixels while the service's catalog holds no episode yet, "
                             f"{TRAINABLE_SIZES} (default 64); after that every grant names the catalog's size, "
                             "which the worker records at")
    parser.add_argument("--realtime", type=flags.realtime, default=0.0, metavar="X",
                        help=f"slow each episode to last at least X * steps / {CONTROL_HZ} seconds ({CONTROL_HZ} Hz "
                             f"control): 1 = a real robot's pace, 2 = half speed, 0.5 = double speed; 0 to "
                             f"{MAX_REALTIME:g} (default 0 = flat out)")
    parser.add_argument("--upload-part-kb", type=upload_part_kb, default=DEFAULT_PART_KB, metavar="KB",
                        help=f"upload an episode bigger than KB kilobytes in parts of KB, each answered before the "
                             f"next is sent: over a slow uplink one part at a time holds the link, not the whole "
                             f"episode, so renewals get through and a lost reply costs one part (1 to {MAX_PART_KB}; "
                             f"default {DEFAULT_PART_KB}); give --timeout more than one part's transfer time")
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                        help="least severe log messages written to stderr (default INFO)")
    parser.set_defaults(worker_prog=parser.prog)


def upload_part_kb(text: str) -> int:
    """``--upload-part-kb``: 1 to MAX_PART_KB."""
    value = flags.positive_int(text)
    if value > MAX_PART_KB:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_PART_KB} (the largest upload), found {value}")
    return value


def config_from_args(args: argparse.Namespace) -> WorkerConfig:
    """Build the WorkerConfig; WorkerError naming the flag (``--id: expected ...``) for a bad value."""
    listen, connect = endpoints.endpoints_from_args(args)
    try:
        given = (("worker_id", args.id, "<host>-<pid>"), ("capabilities", args.capabilities, "anything"))
        for field, value, left_out in given:
            if value is not None and not value.strip():  # (an unset shell variable, say: not the default by stealth)
                raise WorkerError(f"{field}: expected a value, found {value!r} (leave the flag out for {left_out})")
        tasks, shapes = parse_capabilities(args.capabilities or "")
        config = WorkerConfig(worker_id=args.id or "", namespace=args.namespace, mode=args.mode, listen=listen,
                              connect=connect, zenoh_config=args.zenoh_config, tasks=tasks, shapes=shapes,
                              image_size=args.size, max_episodes=args.max_episodes, once=args.once,
                              realtime=args.realtime, timeout_s=args.timeout, part_bytes=args.upload_part_kb * 1024)
    except WorkerError as exc:
        raise WorkerError(flags.naming_flag(str(exc))) from None
    if config.zenoh_config is not None:  # another role's profile config: its lease queries would never be answered
        path, keys = Path(config.zenoh_config), config.keys
        if denied := acl.denied_by_acl(transport.read_config(path), path, keys.lease, keys.namespace, "lease queries"):
            raise WorkerError(f"--zenoh-config: {denied}")
    return config


def run_from_args(args: argparse.Namespace) -> int:
    """Run a worker from parsed flags until it is done or stopped; exit status (2: bad flags)."""
    prog = getattr(args, "worker_prog", "activecollect worker")
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        worker = Worker(config_from_args(args))
    except (WorkerError, transport.SecureConfigError) as exc:
        print(f"{prog}: error: {protocol.one_line(str(exc))}", file=sys.stderr)  # a path may hold a newline
        return 2
    worker.install_signal_handlers()
    try:
        return _work(worker, prog)
    finally:  # it holds nothing now: a stop signal while it exits must not kill it (exit -15 instead of its status)
        signals.ignore_while_exiting([signal.SIGTERM, signal.SIGINT, DRAIN_SIGNAL])


def _work(worker: Worker, prog: str) -> int:
    if early := startup.taken():  # (came during the imports of python -m workers.agent or activecollect worker)
        log.info("worker %s: %s while starting, before it held any request: exiting", worker.config.worker_id,
                 early[0].name)
        return 0
    try:
        worker.run()
    except WorkerError as exc:
        print(f"{prog}: {protocol.one_line(str(exc))}", file=sys.stderr)
        return 1
    if worker.abandoned:
        print(f"{prog}: stopped at once: dropped the episode of {', '.join(worker.abandoned)}, never acknowledged "
              "(the log says whether its request was given back)", file=sys.stderr)
    if worker.dropped:
        print(f"{prog}: gave up {worker.dropped} collected episode(s) the service would not store while draining "
              "(see the log)", file=sys.stderr)
    refused = worker.config.once and worker.refused is not None  # not "no work": a script must tell them apart
    if refused:
        print(f"{prog}: {protocol.one_line(str(worker.refused))}", file=sys.stderr)
    return 1 if worker.abandoned or worker.dropped or refused else 0


def build_parser() -> argparse.ArgumentParser:
    """``python -m workers.agent``'s parser: a bad flag exits 2 in one line, like ``activecollect worker``."""
    parser = flags.Parser(prog="python -m workers.agent", description=DESCRIPTION)
    add_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_from_args(build_parser().parse_args(argv))
