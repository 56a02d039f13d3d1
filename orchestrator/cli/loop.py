"""The closed loop's commands: ``run``, ``retrain`` and ``dashboard`` (``bench loop`` is ``cli/loopbench.py``).

Argument parsing and printing only; each command is one call into
``orchestrator.loop``, ``orchestrator.retrain`` or ``orchestrator.dashboard``.

``run`` and ``retrain`` import their modules (and with them torch, about 2 s) when
they run, so the parsers built here, and every other command, start without it;
their settings come from the torch-free ``orchestrator.loopconfig`` and
``uncertainty.config``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import threading
from collections import Counter

from orchestrator.champion import ChampionScorer, FramesSource, limit_torch_threads
from orchestrator.cli import collect as collect_cli, common
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.loopconfig import RunConfig
from orchestrator.retrainlock import EXIT_BUSY, RetrainBusyError
from orchestrator.retrainjob import quarantined_note
from orchestrator.serviceconfig import ServiceError
from orchestrator.signals import on_stop_signals
from orchestrator.protocol import one_line
from storage.catalog import Catalog
from storage.errors import StorageError
from storage.jsonsafe import finite_json
from uncertainty.config import TrainConfig
from uncertainty.errors import ConfigError, UncertaintyError
# The CLI is the composition root: it alone hands the simulator to the orchestrator's loops.
from workers.collect import EvalSplitConflict


def register(sub: argparse._SubParsersAction) -> None:
    d = RunConfig(data_dir=common.DEFAULT_DATA)
    retrain = vars(retrain_options_parser().parse_args(list(d.retrain_args)))
    p = sub.add_parser("run", help="the whole loop on this machine: service, workers, retrains, report",
                       description="The whole loop on this machine: the service, worker processes over Zenoh on "
                                   "loopback, the eval split (made when missing), a retrain after every round and "
                                   "a report (DATA/reports/<time>/index.html). Each retrain trains "
                                   f"{retrain['members']} members, {retrain['epochs']} epochs, widths "
                                   f"{','.join(map(str, retrain['widths']))} (--retrain-args; `retrain` alone "
                                   f"trains {train_defaults(TrainConfig())}). --budget counts the catalog's "
                                   "training episodes, old and new (quarantined ones too): a run over a finished "
                                   "directory stops at once. Ctrl-C or SIGTERM stops it cleanly (the workers upload "
                                   "the episode in hand, the report is written; exit 130) and the next run resumes; "
                                   "one more while it stops only stops a running retrain, never the report (a "
                                   "terminal's also makes the workers give their episode back unfinished); exit 1 "
                                   "when every retrain of the run failed.")
    common.add_data_arg(p)
    common.add_json_arg(p)
    p.add_argument("--budget", type=common.positive_int, default=d.budget, metavar="N",
                   help=f"stop at this many training episodes (default {d.budget})")
    p.add_argument("--round", type=common.positive_int, default=d.round_episodes, dest="round_episodes", metavar="N",
                   help=f"retrain every N episodes; the next N are planned by the model it made (default "
                        f"{d.round_episodes})")
    p.add_argument("--workers", type=common.positive_int, default=d.workers, metavar="N",
                   help=f"worker processes (default {d.workers})")
    p.add_argument("--planner", choices=("active", "uniform"), default=d.planner,
                   help=f"where episodes start (default {d.planner})")
    common.add_episode_args(p, d.steps, d.image_size)
    p.add_argument("--eval-episodes", type=common.positive_int, default=d.eval_episodes, metavar="N",
                   help=f"episodes in the eval split, made when missing (default {d.eval_episodes})")
    p.add_argument("--eval-seed", type=common.non_negative_int, default=d.eval_seed, metavar="K",
                   help=f"seed of the eval split's start states and policies, as eval-split create --seed "
                        f"(default {d.eval_seed})")
    p.add_argument("--seed", type=common.non_negative_int, default=d.seed, metavar="K",
                   help=f"planner seed (default {d.seed})")
    p.add_argument("--dashboard-port", type=common.dashboard_port, default=d.dashboard_port, metavar="PORT",
                   help=f"dashboard on 127.0.0.1:PORT (0 = any free port, -1 = none; default {d.dashboard_port})")
    add_retrain_args_arg(p, d.retrain_args)
    p.add_argument("--no-progress", action="store_true", help="no live progress line")
    p.set_defaults(func=_run)

    p = sub.add_parser("retrain", help="one retrain job (train, evaluate, gate) under DATA/retrain.lock, then exit",
                       description="One retrain job under DATA/retrain.lock: train a candidate on every train "
                                   "episode, evaluate it on the pinned eval split, and promote it when the gate "
                                   f"allows; then exit. By default it trains {train_defaults(TrainConfig())}. "
                                   f"Exit {EXIT_BUSY} while another job holds the lock (see --wait), 1 when "
                                   "training fails; a job killed before its gate leaves the champion as it was "
                                   "(a candidate it registered is rejected by the next job).")
    _retrain_options(p)
    p.set_defaults(func=_retrain)

    p = sub.add_parser("dashboard", help="serve the read-only dashboard over a data directory",
                       description="Serve the read-only dashboard over --data until Ctrl-C or SIGTERM (exit 0): the "
                                   "HTML page, /api/... "
                                   "JSON and /metrics for Prometheus (here only the gauges the data directory holds; "
                                   "the service's counters come from serve's or run's dashboard). It has no "
                                   "authentication: keep --host on loopback, or behind something that has. Exit 2 "
                                   "when it cannot listen there.")
    common.add_data_arg(p)
    p.add_argument("--host", type=_bind_address, default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=common.tcp_port, default=8765, help="TCP port (default 8765, 0 = any)")
    common.add_dashboard_limit_args(p)
    p.set_defaults(func=_dashboard)


def _bind_address(text: str) -> str:
    """``dashboard --host``: an empty one (an unset shell variable) would bind every interface, unauthenticated."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected an address to bind such as 127.0.0.1, found {text!r} (which "
                                         "would bind every interface: give 0.0.0.0 for that)")
    return text


def add_train_args(p: argparse.ArgumentParser, defaults: TrainConfig | None = None) -> None:
    """Training settings shared by ``retrain`` and ``run`` (the rest keep TrainConfig's defaults)."""
    d = defaults or TrainConfig()
    p.add_argument("--members", type=common.ensemble_size, default=d.members, metavar="K",
                   help=f"ensemble size (default {d.members})")
    p.add_argument("--epochs", type=common.epoch_count, default=d.epochs, metavar="N",
                   help=f"passes over the training windows, at most {common.MAX_EPOCHS} (default {d.epochs})")
    p.add_argument("--batch-size", type=common.positive_int, default=d.batch_size, metavar="N",
                   help=f"windows per member per step (default {d.batch_size})")
    p.add_argument("--lr", type=common.positive_float, default=d.lr, metavar="LR",
                   help=f"peak learning rate (default {d.lr})")
    p.add_argument("--widths", type=common.channel_widths, default=d.widths, metavar="A,B,C",
                   help=f"channel widths of a fresh model (default {','.join(map(str, d.widths))})")
    p.add_argument("--max-windows", type=common.positive_int, default=d.max_windows, metavar="N",
                   help="cap on training windows (a seeded subset; default all)")
    p.add_argument("--seed", type=common.non_negative_int, default=d.seed, metavar="K",
                   help=f"training seed (default {d.seed})")
    p.add_argument("--device", type=common.torch_device, default=d.device,
                   help=f"torch device: auto, cpu or cuda (default {d.device}"
                        f"{': cuda when there is one' if d.device == 'auto' else ''})")
    p.add_argument("--from-champion", action="store_true", default=d.from_champion,
                   help="warm-start from the champion's weights")
    p.add_argument("--variance-head", action="store_true", default=d.variance_head,
                   help="a fresh model's members also predict the variance of their own error "
                        "(eval reports its calibration; scoring still uses the disagreement)")
    p.add_argument("--min-improvement", type=common.fraction, default=d.min_rel_improvement, metavar="FRAC",
                   help=f"the gate's minimum relative h1 MSE improvement, in [0, 1) (default {d.min_rel_improvement})")


def _retrain_options(p: argparse.ArgumentParser) -> None:
    """Every option of ``retrain`` (also what checks ``--retrain-args``)."""
    common.add_data_arg(p)
    common.add_json_arg(p)
    add_train_args(p)
    p.add_argument("--wait", action="store_true",
                   help=f"wait for a running retrain to finish instead of exiting {EXIT_BUSY} at once")
    p.add_argument("--keep-models", type=common.positive_int, default=None, metavar="N",
                   help="after the gate, delete the files of retired and rejected models except the champion's "
                        "rollback chain of N (as 'models prune --keep N'; default: keep every model)")
    p.add_argument("--threads", type=common.torch_threads, default=0, metavar="N",
                   help="torch threads to train with (default 0: torch's own, one per core; serve gives its jobs "
                        "the cores its scoring leaves, see serve --retrain-threads)")


class _RetrainArgsParser(common.Parser):
    """The retrain job's own parser, checking a ``--retrain-args`` string: a usage error is raised, not exited."""

    def error(self, message: str):
        raise argparse.ArgumentTypeError(message)


def retrain_options_parser() -> argparse.ArgumentParser:
    """A parser of the retrain job's options that raises ``ArgumentTypeError`` instead of exiting."""
    parser = _RetrainArgsParser(prog="retrain", add_help=False)
    _retrain_options(parser)
    return parser


#: Set by the scheduler itself (``retrainjob.retrain_command``): in --retrain-args they would train elsewhere
#: or change what the scheduler reads back.
_SCHEDULER_OWNS = ("data", "json", "wait")


def retrain_args(text: str) -> tuple[str, ...]:
    """A ``--retrain-args`` value: shell-split, and checked now by a parser with the retrain job's options
    (abbreviations resolve as they will there), so a bad one is a usage error of the command that was
    given it (exit 2) instead of a failed job at every retrain."""
    try:
        args = tuple(shlex.split(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"cannot split {text!r}: {exc}") from None
    parser = retrain_options_parser()
    unset = object()
    parser.set_defaults(**{dest: unset for dest in _SCHEDULER_OWNS})
    given = vars(parser.parse_args(list(args)))
    for dest in _SCHEDULER_OWNS:
        if given[dest] is not unset:
            raise argparse.ArgumentTypeError(f"--{dest} is decided by the scheduler, not by --retrain-args")
    return args


def train_defaults(cfg: TrainConfig) -> str:
    """``5 members, 8 epochs, widths 16,32,64``: what a retrain job trains when not told otherwise."""
    return f"{cfg.members} members, {cfg.epochs} epochs, widths {','.join(map(str, cfg.widths))}"


def add_retrain_args_arg(p: argparse.ArgumentParser, default: tuple[str, ...]) -> None:
    if default:
        what = (f"they REPLACE this command's default, '{' '.join(default)}', and are not added to it: repeat "
                "those of its options you want kept")
    else:
        what = f"an option not given keeps retrain's own default ({train_defaults(TrainConfig())})"
    p.add_argument("--retrain-args", type=retrain_args, default=default, metavar="'ARGS'",
                   help=f"arguments of each retrain job, as one string (see 'activecollect retrain --help'); {what}. "
                        "One option alone needs '=': --retrain-args=--from-champion")


def train_config(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(members=args.members, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                       widths=args.widths, max_windows=args.max_windows, seed=args.seed, device=args.device,
                       from_champion=args.from_champion, min_rel_improvement=args.min_improvement,
                       variance_head=args.variance_head, progress=False)


#: ``run``'s flag for each parameter of a pinned eval split (``workers.collect.eval_split_params``).
RUN_SPLIT_FLAGS = {"image_size": "--image-size", "steps": "--steps", "episodes": "--eval-episodes",
                   "seed": "--eval-seed"}


def _run(args: argparse.Namespace) -> int:
    try:
        cfg = RunConfig(data_dir=args.data, budget=args.budget, round_episodes=args.round_episodes,
                        workers=args.workers, planner=args.planner, steps=args.steps,
                        image_size=args.image_size, eval_episodes=args.eval_episodes, eval_seed=args.eval_seed,
                        seed=args.seed, dashboard_port=args.dashboard_port, retrain_args=args.retrain_args,
                        progress=not args.no_progress)
    except ValueError as exc:
        raise common.config_error(exc, {"budget": "--budget", "workers": "--workers", "steps": "--steps",
                                        "planner": "--planner"}) from None
    pinned = collect_cli.refuse_other_settings(cfg.data_dir, RUN_SPLIT_FLAGS, "run", "this run asks for",
                                               "--image-size", episodes=cfg.eval_episodes, seed=cfg.eval_seed,
                                               steps=cfg.steps, image_size=cfg.image_size)
    if pinned is None:  # the split this run would make: train episodes already recording some refuse it (exit 2)
        collect_cli.refuse_eval_replays(cfg.data_dir, cfg.eval_episodes, cfg.eval_seed, cfg.image_size,
                                        "--eval-seed")
    from orchestrator.loop import LoopError, LoopRun  # torch: imported once the arguments are known good
    run = LoopRun(cfg, collect_cli.make_eval_split, announce=lambda line: print(line, file=sys.stderr, flush=True))
    try:
        result = run.run()
    except EvalSplitConflict as exc:  # pinned by another process since the check
        raise collect_cli.eval_split_refusal(cfg.data_dir, exc, RUN_SPLIT_FLAGS, "run", "this run asks for") from None
    except (LoopError, ServiceError) as exc:  # every worker died, the service would not start: stopped already
        print(one_line(f"activecollect run: {exc}"), file=sys.stderr)
        return 1
    if args.json:
        common.print_json(finite_json(result.to_json()))  # (a retrain's h5/h10 of episodes too short: NaN)
    else:
        h1 = "-" if result.champion_h1_mse is None else f"{result.champion_h1_mse:.4e}"
        outcomes = Counter(r["status"] for r in result.retrains)
        how = f" ({', '.join(f'{n} {status}' for status, n in outcomes.items())})" if outcomes else ""
        print(f"{'interrupted' if result.interrupted else 'done'}: {result.episodes} episodes ({result.collected} "
              f"collected by this run), {len(result.retrains)} retrains{how}, champion {result.champion or '-'} "
              f"(eval h1 MSE {h1}), {result.seconds:.0f} s")
        print(f"report: {result.report}")
    if result.interrupted:  # by Ctrl-C or SIGTERM alike, as serve makes no difference between them
        return 130
    learned = [r for r in result.retrains if r["status"] in ("promoted", "rejected")]
    if result.retrains and not learned:  # no model came of this run: not a success, whatever it collected
        outcomes = Counter(r["status"] for r in result.retrains)
        print(one_line(f"activecollect run: every retrain of this run failed "
                       f"({', '.join(f'{n} {status}' for status, n in outcomes.items())}; the last: "
                       f"{result.retrains[-1]['reason'] or '-'}); their logs are in {cfg.data_dir / 'logs'}"),
              file=sys.stderr)
        return 1
    return 0


def _retrain(args: argparse.Namespace) -> int:
    try:
        cfg = train_config(args)
    except ConfigError as exc:
        raise common.config_error(exc, common.TRAIN_FLAGS) from None
    common.require_catalog(args.data)  # checked before the retrain lock would make the directory
    # torch: imported once the arguments are known good (start-up cost)
    from orchestrator.retrain import abandoned_note, run_retrain
    limit_torch_threads(args.threads)
    try:
        result = run_retrain(args.data, cfg, wait=args.wait, keep_models=args.keep_models)
    except RetrainBusyError as exc:
        print(f"activecollect retrain: {exc}", file=sys.stderr)
        return EXIT_BUSY
    except (UncertaintyError, StorageError) as exc:
        print(f"activecollect retrain: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        # one line, so a scheduler reading the job's stdout finds it whatever was printed before
        print(json.dumps(finite_json(result), default=str))  # strict JSON: NaN (h10 of short episodes) as null
    else:
        verdict = "promoted" if result["promoted"] else "not promoted"
        print(f"{result['version']}: {verdict}: {result['reason'].removeprefix('promoted: ')}")  # (the gate's words)
        print(f"  h1_mse {result['metrics'].get('h1_mse')}  h5_mse {result['metrics'].get('h5_mse')}  "
              f"champion {result['champion']}")
        if result["abandoned"]:
            print(f"  {abandoned_note(result['abandoned'])}")
        if result["pruned"]:
            print(f"  pruned the files of {', '.join(result['pruned'])}")
    if result["quarantined"]:
        print(f"activecollect retrain: warning: {quarantined_note(result['quarantined'])}", file=sys.stderr)
    if result["prune_error"]:
        print(f"activecollect retrain: warning: {result['prune_error']}", file=sys.stderr)
    return 0


def _dashboard(args: argparse.Namespace) -> int:
    common.require_catalog(args.data)
    frames = FramesSource(ChampionScorer(args.data), Catalog(args.data, make_episodes_dir=False))
    config = DashboardConfig(host=args.host, port=args.port, max_connections=args.max_connections,
                             request_timeout_s=args.request_timeout)
    dash = Dashboard(config, DataSources(args.data, frames_png=frames).sources())
    try:
        dash.start()
    except OSError as exc:
        raise common.UsageError(f"cannot serve on {args.host}:{args.port}: {exc.strerror}") from None
    stop = threading.Event()
    restore = on_stop_signals(stop.set)  # SIGTERM (a supervisor's) stops it as Ctrl-C does: exit 0, as serve
    print(f"dashboard on {dash.url} (Ctrl-C or SIGTERM to stop)", flush=True)
    try:
        stop.wait()
    finally:
        dash.stop()
        restore()
    return 0
