"""The closed loop's commands: ``run``, ``retrain``, ``dashboard`` and ``bench loop``.

Argument parsing and printing only; each command is one call into
``orchestrator.loop``, ``orchestrator.retrain``, ``orchestrator.dashboard`` or
``orchestrator.loopbench``.

``run``, ``retrain`` and ``bench loop`` import their modules (and with them torch,
about 2 s) when they run, so the parsers built here, and every other command,
start without it; their settings come from the torch-free ``orchestrator.loopconfig``
and ``uncertainty.config``.
"""

from __future__ import annotations

import argparse
import functools
import json
import shlex
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from orchestrator.champion import ChampionScorer, FramesSource
from orchestrator.cli import common
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.loopconfig import SIGNALS, LoopBenchConfig, RunConfig
from orchestrator.scheduler import EXIT_BUSY, RetrainBusyError, quarantined_note
from storage.catalog import Catalog
from storage.errors import StorageError
from storage.requests import Request
from storage.records import Episode
from uncertainty.config import TrainConfig
from uncertainty.errors import ConfigError, UncertaintyError
# The CLI is the composition root: it alone hands the simulator to the orchestrator's loops.
from workers.collect import EvalSplitConflict, collect_episode, create_eval_split


def register(sub: argparse._SubParsersAction) -> None:
    d = RunConfig(data_dir=common.DEFAULT_DATA)
    p = sub.add_parser("run", help="the whole loop on this machine: service, workers, retrains, report")
    common.add_data_arg(p)
    common.add_json_arg(p)
    p.add_argument("--budget", type=common.positive_int, default=d.budget,
                   help=f"stop at this many training episodes (default {d.budget})")
    p.add_argument("--round", type=common.positive_int, default=d.round_episodes, dest="round_episodes",
                   help=f"retrain every N episodes; the next N are planned by the model it made (default "
                        f"{d.round_episodes})")
    p.add_argument("--workers", type=common.positive_int, default=d.workers,
                   help=f"worker processes (default {d.workers})")
    p.add_argument("--planner", choices=("active", "uniform"), default=d.planner,
                   help=f"where episodes start (default {d.planner})")
    p.add_argument("--steps", type=common.positive_int, default=d.steps, help=f"steps per episode (default {d.steps})")
    p.add_argument("--image-size", type=common.positive_int, default=d.image_size,
                   help=f"frame size in pixels (default {d.image_size})")
    p.add_argument("--eval-episodes", type=common.positive_int, default=d.eval_episodes,
                   help=f"episodes in the eval split, made when missing (default {d.eval_episodes})")
    p.add_argument("--seed", type=common.non_negative_int, default=d.seed, help=f"planner seed (default {d.seed})")
    p.add_argument("--dashboard-port", type=int, default=d.dashboard_port,
                   help=f"dashboard port on 127.0.0.1 (default {d.dashboard_port}; 0 any, -1 off)")
    add_retrain_args_arg(p, d.retrain_args)
    p.add_argument("--no-progress", action="store_true", help="no live progress line")
    p.set_defaults(func=_run)

    p = sub.add_parser("retrain", help="one retrain job (train, evaluate, gate) under DATA/retrain.lock, then exit")
    _retrain_options(p)
    p.set_defaults(func=_retrain)

    p = sub.add_parser("dashboard", help="serve the read-only dashboard over a data directory")
    common.add_data_arg(p)
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=common.tcp_port, default=8765, help="TCP port (default 8765, 0 = any)")
    common.add_dashboard_limit_args(p)
    p.set_defaults(func=_dashboard)


def register_bench(bench: argparse._SubParsersAction) -> None:
    d = LoopBenchConfig()
    p = bench.add_parser("loop", help="active vs uniform planner: eval error per episodes collected")
    common.add_json_arg(p)
    p.add_argument("--seeds", type=common.positive_int, default=len(d.seeds),
                   help=f"seeds 0..N-1, one run of each arm per seed (default {len(d.seeds)})")
    p.add_argument("--budget", type=common.positive_int, default=d.budget,
                   help=f"training episodes per arm (default {d.budget})")
    p.add_argument("--round", type=common.positive_int, default=d.round_episodes, dest="round_episodes",
                   help=f"retrain every N episodes (default {d.round_episodes})")
    p.add_argument("--steps", type=common.positive_int, default=d.steps, help=f"steps per episode (default {d.steps})")
    p.add_argument("--image-size", type=common.positive_int, default=d.image_size,
                   help=f"frame size in pixels (default {d.image_size})")
    p.add_argument("--epochs", type=common.positive_int, default=d.train.epochs,
                   help=f"training epochs per retrain (default {d.train.epochs})")
    p.add_argument("--members", type=common.positive_int, default=d.train.members,
                   help=f"ensemble size (default {d.train.members})")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=d.train.device, help="torch device")
    p.add_argument("--signal", choices=SIGNALS, default=d.signal,
                   help=f"what the active arm ranks steps by (default {d.signal})")
    p.add_argument("--active-policy", action="store_true", default=d.active_policy,
                   help="let the active arm also choose each episode's collection policy (push or random "
                        "waypoints), favouring the one whose recent episodes the champion disagrees on most "
                        f"(at least {d.active.policy_floor:.0%}% each); the uniform arm keeps the mix")
    p.add_argument("--variance-head", action="store_true", default=d.train.variance_head,
                   help="both arms train members that also predict their own error (the active arm "
                        "still scores by disagreement)")
    p.add_argument("--random-physics", action="store_true", default=d.random_physics,
                   help="make physics (mass, friction, ground friction) part of the task space: uniform and "
                        "seed episodes and the eval split draw them uniformly over their ranges, the active "
                        "arm keeps an uncertain state's physics (default: every episode at the defaults)")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (default ./activecollect-bench/loop-<timestamp>)")
    p.set_defaults(func=_bench_loop)


def bench_collect(request: Request, seed: int, image_size: int) -> Episode:
    """``loopbench.Collect`` over the simulator: the episode a request asks for, collected here."""
    return collect_episode(start_state=request.start_state, policy=request.policy,
                           policy_params=request.policy_params, seed=seed, steps=request.steps,
                           image_size=image_size, action_prefix=request.action_prefix or None,
                           request_id=request.id, worker_id="bench",
                           model_version=str(request.reason.get("model_version") or ""))


def bench_eval_split(catalog: Catalog, episodes: int, seed: int, steps: int, image_size: int,
                     random_physics: bool = False) -> str:
    return create_eval_split(catalog, episodes=episodes, seed=seed, steps=steps, image_size=image_size,
                             random_physics=random_physics)


def _bench_loop(args: argparse.Namespace) -> int:
    from orchestrator.loopbench import run_bench  # torch: imported when the command runs (start-up cost)
    d = LoopBenchConfig()
    train = TrainConfig(**{**d.train.to_dict(), "epochs": args.epochs, "members": args.members,
                           "device": args.device, "widths": d.train.widths,
                           "variance_head": args.variance_head})
    try:
        cfg = LoopBenchConfig(seeds=tuple(range(args.seeds)), budget=args.budget,
                              round_episodes=args.round_episodes, steps=args.steps,
                              image_size=args.image_size, train=train, signal=args.signal,
                              active_policy=args.active_policy, random_physics=args.random_physics)
    except ValueError as exc:
        raise common.UsageError(str(exc)) from None
    out = args.out or Path("activecollect-bench") / time.strftime("loop-%Y%m%dT%H%M%S")
    if (out / "summary.json").exists():
        raise common.UsageError(f"{out} already holds a bench loop result; give a fresh --out")
    log = (lambda line: print(line, file=sys.stderr, flush=True))
    summary = run_bench(cfg, out, bench_collect, functools.partial(bench_eval_split, random_physics=cfg.random_physics),
                        log=log)
    if args.json:
        common.print_json(summary)
        return 0
    for metric in ("h1", "h5"):
        h = summary[metric]["headline"]
        print(f"{metric} MSE final: active {h['active_final']:.4e}  uniform {h['uniform_final']:.4e}")
        print(f"  episodes to reach the other arm's final error (budget {h['budget']}): uniform "
              f"{_eps(h['uniform_episodes_to_match_active'])}, active {_eps(h['active_episodes_to_match_uniform'])}")
    print(f"plot: {summary['plot']}\nsummary: {out / 'summary.json'}  ({summary['seconds']:.0f} s)")
    return 0


def _eps(v: float | None) -> str:
    return "not within the budget" if v is None else f"{v:.1f}"


def add_train_args(p: argparse.ArgumentParser, defaults: TrainConfig | None = None) -> None:
    """Training settings shared by ``retrain`` and ``run`` (the rest keep TrainConfig's defaults)."""
    d = defaults or TrainConfig()
    p.add_argument("--members", type=common.positive_int, default=d.members, help=f"ensemble size (default {d.members})")
    p.add_argument("--epochs", type=common.positive_int, default=d.epochs, help=f"epochs (default {d.epochs})")
    p.add_argument("--batch-size", type=common.positive_int, default=d.batch_size,
                   help=f"windows per member per step (default {d.batch_size})")
    p.add_argument("--lr", type=common.positive_float, default=d.lr, help=f"peak learning rate (default {d.lr})")
    p.add_argument("--widths", type=_widths, default=d.widths,
                   help=f"channel widths A,B,C of a fresh model (default {','.join(map(str, d.widths))})")
    p.add_argument("--max-windows", type=common.positive_int, default=d.max_windows,
                   help="cap on training windows (a seeded subset; default all)")
    p.add_argument("--seed", type=common.non_negative_int, default=d.seed, help=f"training seed (default {d.seed})")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=d.device, help="torch device")
    p.add_argument("--from-champion", action="store_true", default=d.from_champion,
                   help="warm-start from the champion's weights")
    p.add_argument("--variance-head", action="store_true", default=d.variance_head,
                   help="a fresh model's members also predict the variance of their own error "
                        "(eval reports its calibration; scoring still uses the disagreement)")
    p.add_argument("--min-improvement", type=common.finite_float, default=d.min_rel_improvement,
                   help=f"the gate's minimum relative h1 MSE improvement (default {d.min_rel_improvement})")


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


class _RetrainArgsParser(common.Parser):
    """The retrain job's own parser, checking a ``--retrain-args`` string: a usage error is raised, not exited."""

    def error(self, message: str):
        raise argparse.ArgumentTypeError(message)


#: Set by the scheduler itself (``scheduler.retrain_command``): in --retrain-args they would train elsewhere
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
    parser = _RetrainArgsParser(prog="retrain", add_help=False)
    _retrain_options(parser)
    unset = object()
    parser.set_defaults(**{dest: unset for dest in _SCHEDULER_OWNS})
    given = vars(parser.parse_args(list(args)))
    for dest in _SCHEDULER_OWNS:
        if given[dest] is not unset:
            raise argparse.ArgumentTypeError(f"--{dest} is decided by the scheduler, not by --retrain-args")
    return args


def add_retrain_args_arg(p: argparse.ArgumentParser, default: tuple[str, ...]) -> None:
    shown = " ".join(default) or "retrain's own defaults"
    p.add_argument("--retrain-args", type=retrain_args, default=default, metavar="'ARGS'",
                   help=f"arguments of each retrain job, as one string (see 'activecollect retrain --help'; "
                        f"default: {shown}); one option alone needs '=': --retrain-args=--from-champion")


def train_config(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(members=args.members, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                       widths=args.widths, max_windows=args.max_windows, seed=args.seed, device=args.device,
                       from_champion=args.from_champion, min_rel_improvement=args.min_improvement,
                       variance_head=args.variance_head, progress=False)


def _widths(text: str) -> tuple[int, int, int]:
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three integers like 8,16,32, found {text!r}") from None
    if len(widths) != 3 or min(widths) < 1:
        raise argparse.ArgumentTypeError(f"expected three positive integers like 8,16,32, found {text!r}")
    return widths  # type: ignore[return-value]


def _run(args: argparse.Namespace) -> int:
    from orchestrator.loop import LoopRun  # torch: imported when the command runs (start-up cost)
    try:
        cfg = RunConfig(data_dir=args.data, budget=args.budget, round_episodes=args.round_episodes,
                        workers=args.workers, planner=args.planner, steps=args.steps,
                        image_size=args.image_size, eval_episodes=args.eval_episodes, seed=args.seed,
                        dashboard_port=args.dashboard_port, retrain_args=args.retrain_args,
                        progress=not args.no_progress)
    except ValueError as exc:
        raise common.UsageError(str(exc)) from None
    common.require_frame_size(args.data, args.image_size, "--image-size")
    run = LoopRun(cfg, bench_eval_split, announce=lambda line: print(line, file=sys.stderr, flush=True))
    try:
        result = run.run()
    except EvalSplitConflict as exc:  # this directory's split was made with other --steps / --eval-episodes
        raise common.UsageError(f"{exc}; give the same settings, or another --data") from None
    if args.json:
        common.print_json(result.to_json())
    else:
        h1 = "-" if result.champion_h1_mse is None else f"{result.champion_h1_mse:.4e}"
        outcomes = Counter(r["status"] for r in result.retrains)
        how = f" ({', '.join(f'{n} {status}' for status, n in outcomes.items())})" if outcomes else ""
        print(f"{'interrupted' if result.interrupted else 'done'}: {result.episodes} episodes, "
              f"{len(result.retrains)} retrains{how}, champion {result.champion or '-'} (eval h1 MSE {h1}), "
              f"{result.seconds:.0f} s")
        print(f"report: {result.report}")
    return 130 if result.interrupted else 0


def _retrain(args: argparse.Namespace) -> int:
    try:
        cfg = train_config(args)
    except ConfigError as exc:
        raise common.UsageError(str(exc)) from None
    common.require_catalog(args.data)  # checked before the retrain lock would make the directory
    # torch: imported once the arguments are known good (start-up cost)
    from orchestrator.retrain import abandoned_note, run_retrain
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
        print(json.dumps(result, default=str, allow_nan=True))
    else:
        verdict = "promoted" if result["promoted"] else "not promoted"
        print(f"{result['version']}: {verdict}: {result['reason']}")
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
    frames = FramesSource(ChampionScorer(args.data), Catalog(args.data))
    config = DashboardConfig(host=args.host, port=args.port, max_connections=args.max_connections,
                             request_timeout_s=args.request_timeout)
    dash = Dashboard(config, DataSources(args.data, frames_png=frames).sources())
    try:
        dash.start()
    except OSError as exc:
        raise common.UsageError(f"cannot serve on {args.host}:{args.port}: {exc.strerror}") from None
    print(f"dashboard on {dash.url} (Ctrl-C to stop)", flush=True)
    try:
        threading.Event().wait()
    finally:
        dash.stop()
    return 0
