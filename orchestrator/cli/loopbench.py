"""``activecollect bench loop``: the active planner against the uniform planner, collected with the simulator.

Argument parsing and printing only; the comparison is ``orchestrator.loopbench.run_bench``, imported (with
torch, about 2 s) once the arguments are known good. Its settings come from the torch-free
``orchestrator.loopconfig``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import time
from pathlib import Path
from typing import Mapping

from orchestrator.cli import collect as collect_cli, common
from orchestrator.loopconfig import PALETTES, SIGNALS, LoopBenchConfig
from orchestrator.protocol import SHAPES
from storage.jsonsafe import finite_json
from storage.records import Episode
from storage.requests import Request
from uncertainty.config import TrainConfig
from uncertainty.errors import ConfigError
# The CLI is the composition root: it alone hands the simulator to the orchestrator's loops.
from workers.collect import collect_episode


def register_bench(bench: argparse._SubParsersAction) -> None:
    d = LoopBenchConfig()
    p = bench.add_parser("loop", help="active vs uniform planner: eval error per episodes collected",
                         description="Active vs uniform planner: for each seed, both arms collect --budget episodes "
                                     "in rounds of --round with the simulator, retraining after each round, and "
                                     "the eval error is recorded per episodes collected; summary.json and a plot "
                                     "go to --out. Takes minutes. Ctrl-C or SIGTERM stops the arms and "
                                     "summarises the rounds both arms of a seed had finished (exit 130 / 143); "
                                     "so does an arm that fails (exit 1). A run killed outright (SIGKILL, the "
                                     "machine lost) is summarised afterwards by `bench loop-summary DIR`.")
    common.add_json_arg(p)
    p.add_argument("--seeds", type=_seed_count, default=len(d.seeds), metavar="N",
                   help=f"seeds 0..N-1, one run of each arm per seed, at most {MAX_SEEDS} (default {len(d.seeds)})")
    p.add_argument("--budget", type=common.positive_int, default=d.budget, metavar="N",
                   help=f"training episodes per arm, at least 2 rounds (default {d.budget})")
    p.add_argument("--round", type=common.positive_int, default=d.round_episodes, dest="round_episodes", metavar="N",
                   help=f"retrain every N episodes (default {d.round_episodes})")
    common.add_episode_args(p, d.steps, d.image_size)
    p.add_argument("--epochs", type=common.epoch_count, default=d.train.epochs, metavar="N",
                   help=f"training epochs per retrain (default {d.train.epochs})")
    p.add_argument("--members", type=common.ensemble_size, default=d.train.members, metavar="K",
                   help=f"ensemble size (default {d.train.members})")
    p.add_argument("--widths", type=common.channel_widths, default=d.train.widths, metavar="A,B,C",
                   help=f"the members' channel widths (default {','.join(map(str, d.train.widths))}; `train`'s "
                        f"are {','.join(map(str, TrainConfig().widths))})")
    p.add_argument("--batch-size", type=common.positive_int, default=d.train.batch_size, metavar="N",
                   help=f"windows per member per step (default {d.train.batch_size})")
    p.add_argument("--lr", type=common.positive_float, default=d.train.lr, metavar="LR",
                   help=f"peak learning rate (default {d.train.lr})")
    p.add_argument("--device", type=common.torch_device, default=d.train.device,
                   help=f"torch device: auto, cpu or cuda (default {d.train.device}; auto: cuda when there is "
                        "one)")
    p.add_argument("--signal", choices=SIGNALS, default=d.signal,
                   help=f"what the active arm ranks steps by (default {d.signal}; error: the champion's actual "
                        "error on the recorded frames; predicted, total: the variance head's, needs "
                        "--variance-head)")
    p.add_argument("--active-policy", action="store_true", default=d.active_policy,
                   help="let the active arm also choose each episode's collection policy (push or random "
                        "waypoints), favouring the one whose recent episodes the champion disagrees on most "
                        f"(at least {d.active.policy_floor:.0%}% each); the uniform arm keeps the mix")
    p.add_argument("--variance-head", action="store_true", default=d.train.variance_head,
                   help="both arms train members that also predict their own error (the active arm "
                        "ranks by it only with --signal predicted or total)")
    p.add_argument("--within-policy", action="store_true", default=d.within_policy,
                   help="the active arm ranks each step against its own policy's steps (its score over the "
                        f"mean score of the last {d.active.policy_window} episodes of that policy the champion "
                        "scored), so the policy that moves more does not take every request")
    p.add_argument("--random-physics", action="store_true", default=d.random_physics,
                   help="make physics (mass, friction, ground friction) part of the task space: uniform and "
                        "seed episodes and the eval split draw them uniformly over their ranges, the active "
                        "arm keeps an uncertain state's physics (default: every episode at the defaults)")
    p.add_argument("--shape-weights", type=shape_weights, default=d.shape_weights, metavar="S=W,...",
                   help="the uniform arm, the seed rounds and the uniform requests that fill an active round "
                        "the planner left short (but with --shapes-by-progress, whose fill keeps each "
                        "shape's quota) draw shapes with these relative weights, e.g. "
                        f"T=7,box=1,L=1,disk=1 (shapes {', '.join(SHAPES)}; one left out weighs 0), while the "
                        "eval split keeps every shape equally: a usual task mix that differs from what the "
                        "model is judged on (default: every shape equally likely)")
    p.add_argument("--palette", choices=PALETTES, default=d.palette,
                   help="object colours in both arms and the eval split: all alike, as the service draws them, "
                        "or one per shape, so that the shapes also look different (default "
                        f"{d.palette})")
    p.add_argument("--max-shape-share", type=common.share, default=d.active.max_shape_share, metavar="F",
                   help="the active planner gives at most this share of the requests it picks in a round to one "
                        f"shape, rounded up, at least 1 (default {d.active.max_shape_share}; 1 = no cap); a round it "
                        "leaves short is filled with uniform requests")
    p.add_argument("--repeats", type=common.positive_int, default=d.active.repeats, metavar="N",
                   help="the active planner may ask for one uncertain object pose up to N times (each with a new "
                        f"pusher; default {d.active.repeats}: each pose once)")
    p.add_argument("--min-per-shape", type=common.non_negative_int, default=d.active.min_per_shape, metavar="N",
                   help="when the active planner's picks leave a round short, first fill it with uniform starts "
                        "until every shape has N requests in the round (its picks count; the shape with the "
                        "fewest first), then the rest with the usual mix (default "
                        f"{d.active.min_per_shape}: off; see BENCHMARKS, \"What made the accidental repeats "
                        "pay\"; not with --shapes-by-progress)")
    p.add_argument("--shapes-by-progress", action="store_true", default=d.shapes_by_progress,
                   help="instead of that cap, the active planner splits each round over the shapes by how much "
                        "the champion's error on a shape's recent episodes fell once it trained on them, beyond "
                        "the shape whose error fell least (what data of that shape buys; a share "
                        "--progress-floor of each round split equally), then picks each shape's states by the "
                        "signal; a shape without candidates gets uniform starts of that shape (an experiment)")
    p.add_argument("--progress-floor", type=common.unit, default=None, metavar="F",
                   help="with --shapes-by-progress, the share of each round split equally over the shapes "
                        f"(default {d.active.progress_floor}; 1 = every shape equally, whatever the data buys; "
                        "0 = by progress only)")
    p.add_argument("--progress-horizon", type=common.positive_int, default=None, metavar="H",
                   help="with --shapes-by-progress, the horizon of the error whose fall is measured (default "
                        f"{d.active.progress_horizon}, the gate's; a longer one weighs the dynamics more; at most "
                        "--steps minus the model's context frames)")
    p.add_argument("--deterministic", action="store_true",
                   help="only deterministic torch algorithms in each arm, so that two runs of one configuration "
                        "give the same figures on a GPU too (they do on the CPU without it); slower on a GPU")
    p.add_argument("--jobs", type=common.positive_int, default=1, metavar="N",
                   help="run the seeds' arms in N processes at once, each arm in its own (default 1: one after "
                        "the other in this process); on the CPU an arm's figures are the same either way at the "
                        "same --threads")
    p.add_argument("--threads", type=common.torch_threads, default=0, metavar="N",
                   help="torch threads of each arm (default 0: torch's own, a thread per core, with --jobs 1; "
                        "the cores shared out with more)")
    p.add_argument("--out", type=lambda t: common.directory_path(t, "an output directory"), metavar="DIR",
                   help="a new or empty output directory (default ./activecollect-bench/loop-<timestamp>)")
    p.set_defaults(func=_bench_loop)
    p = bench.add_parser("loop-summary", help="summarise a bench loop run that was killed, or is still running",
                         description="Writes summary.json and loop.png in DIR, the --out of a bench loop run that "
                                     "could not write them (killed outright: SIGKILL, an out-of-memory kill, the "
                                     "machine lost) or is still running, from the configuration it wrote when it "
                                     "started and the points each arm wrote after each retrain: the comparison "
                                     "over the rounds both arms of a seed finished, marked \"rebuilt\" (and "
                                     "\"interrupted\" unless every arm reached the budget). A summary the run "
                                     "wrote itself is kept (exit 1); a run still going replaces the rebuilt one "
                                     "with its own when it ends. Needs no torch: seconds.")
    common.add_json_arg(p)
    p.add_argument("dir", type=lambda t: common.directory_path(t, "a bench loop output directory"), metavar="DIR",
                   help="the bench loop run's --out")
    p.set_defaults(func=_loop_summary)


#: The most seeds one run compares: each is two arms of minutes (10^20 was a traceback, 10^10 a hang listing them).
MAX_SEEDS = 1000


def _seed_count(text: str) -> int:
    return common.int_in(text, 1, MAX_SEEDS, "a positive integer", "seeds (each is two arms of minutes)")


def shape_weights(text: str) -> tuple[float, ...]:
    """``--shape-weights``: ``SHAPE=W,...`` to one weight per ``protocol.SHAPES`` (a shape left out weighs 0)."""
    weights = dict.fromkeys(SHAPES, 0.0)
    given: set[str] = set()
    for item in text.split(","):
        name, eq, value = item.partition("=")
        name = name.strip()
        if not eq or name not in weights:
            raise argparse.ArgumentTypeError(f"expected SHAPE=WEIGHT,... with shapes from {', '.join(SHAPES)}, "
                                             f"found {item.strip()!r}")
        if name in given:
            raise argparse.ArgumentTypeError(f"{name} is given twice in {text!r}")
        given.add(name)
        try:
            weights[name] = common.finite_float(value)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(f"weight of {name}: {exc}") from None
        if weights[name] < 0:
            raise argparse.ArgumentTypeError(f"expected a weight >= 0 for {name}, found {value.strip()!r}")
    if not 0 < sum(weights.values()) < math.inf:
        raise argparse.ArgumentTypeError(f"expected at least one positive weight and a finite sum, found {text!r}")
    return tuple(weights.values())


def bench_collect(request: Request, seed: int, image_size: int,
                  palette: Mapping[str, tuple[int, int, int]] | None = None) -> Episode:
    """``loopbench.Collect`` over the simulator: the episode a request asks for, collected here."""
    return collect_episode(start_state=request.start_state, policy=request.policy,
                           policy_params=request.policy_params, seed=seed, steps=request.steps,
                           image_size=image_size, action_prefix=request.action_prefix or None,
                           request_id=request.id, worker_id="bench",
                           model_version=str(request.reason.get("model_version") or ""), palette=palette)


def _bench_loop(args: argparse.Namespace) -> int:
    d = LoopBenchConfig()
    progress = {k: getattr(args, k) for k in ("progress_floor", "progress_horizon") if getattr(args, k) is not None}
    if progress and not args.shapes_by_progress:
        raise common.UsageError(f"--{next(iter(progress)).replace('_', '-')} only applies with --shapes-by-progress")
    try:
        train = TrainConfig(**{**d.train.to_dict(), "epochs": args.epochs, "members": args.members,
                               "device": args.device, "widths": args.widths,
                               "batch_size": args.batch_size, "lr": args.lr,
                               "variance_head": args.variance_head})
        cfg = LoopBenchConfig(seeds=tuple(range(args.seeds)), budget=args.budget,
                              round_episodes=args.round_episodes, steps=args.steps,
                              image_size=args.image_size, train=train, signal=args.signal,
                              active_policy=args.active_policy, random_physics=args.random_physics,
                              within_policy=args.within_policy, shape_weights=args.shape_weights,
                              palette=args.palette, shapes_by_progress=args.shapes_by_progress,
                              deterministic=args.deterministic,
                              active=dataclasses.replace(d.active, max_shape_share=args.max_shape_share,
                                                         repeats=args.repeats, min_per_shape=args.min_per_shape,
                                                         **progress))
    except (ValueError, ConfigError) as exc:
        raise common.config_error(exc, {"budget": "--budget", "seeds": "--seeds", "members": "--members",
                                        "epochs": "--epochs", "signal": "--signal", "lr": "--lr", "widths": "--widths",
                                        "min_per_shape": "--min-per-shape",
                                        "shapes_by_progress": "--shapes-by-progress"}) from None
    out = args.out or Path("activecollect-bench") / time.strftime("loop-%Y%m%dT%H%M%S")
    if (out / "summary.json").exists() or any(out.glob("seed*/*/catalog.sqlite")):  # (or a stopped run's arms)
        raise common.UsageError(f"{out} already holds a bench loop result, or a stopped run's; give a fresh --out")
    held = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if held:  # a data directory, a home: its config.json, summary.json and loop.png would replace theirs
        raise common.UsageError(f"{out} is not empty (it holds {', '.join(held[:3])}{', ...' if held[3:] else ''}); "
                                "give a new or empty --out")
    # torch: imported once the arguments are known good (start-up cost)
    from orchestrator.loopbench import ArmFailed, log_stderr, run_bench
    try:
        summary = run_bench(cfg, out, bench_collect, collect_cli.make_eval_split, log=log_stderr, jobs=args.jobs,
                            threads=args.threads)
    except ArmFailed as exc:
        kept = f"; the rounds finished before are in {out / 'summary.json'}" if exc.summary else ""
        print(f"activecollect: {exc}{kept}", file=sys.stderr)
        return 1
    if args.json:
        common.print_json(finite_json(summary))  # (h5 of episodes too short for it is NaN: not JSON)
    else:
        _print_summary(summary, out)
    if summary["interrupted"]:  # (the arms are stopped; what they had finished is summarised)
        kept = f"the finished rounds are in {out / 'summary.json'}" if summary["points"] else "no round had finished"
        print(f"activecollect: interrupted ({summary['stopped_by']}): {kept}", file=sys.stderr)
        return 128 + int(getattr(signal, summary["stopped_by"]))
    return 0


def _loop_summary(args: argparse.Namespace) -> int:
    from orchestrator.loopsummary import CONFIG, SummaryError, rebuild  # (matplotlib: only for this command)
    if not args.dir.is_dir():
        raise common.UsageError(f"no such directory: {args.dir}")
    if not (args.dir / CONFIG).is_file():
        raise common.UsageError(f"{args.dir} holds no {CONFIG}: not the --out of a bench loop run (or of one from "
                                "before 2026-11-27, which did not write it)")
    try:
        summary = rebuild(args.dir)
    except SummaryError as exc:
        print(f"activecollect: cannot summarise: {exc}", file=sys.stderr)
        return 1
    if args.json:
        common.print_json(finite_json(summary))
    else:
        _print_summary(summary, args.dir)
    return 0


def _print_summary(summary: dict, out: Path) -> None:
    if not summary["points"]:  # (stopped before any round: the message says so)
        return
    if summary.get("rebuilt"):
        print("rebuilt from the points the arms wrote (the run did not summarise itself)")
    if summary["interrupted"]:
        by = f" by {summary['stopped_by']}" if summary["stopped_by"] else ""
        print(f"stopped{by}: the comparison covers the rounds both arms of a seed finished")
    upto = "both arms' last round at" if summary["interrupted"] else "budget"
    for metric in ("h1", "h5"):
        h = summary[metric]["headline"]
        if h is None:
            print(f"{metric}: no seed has a round that both arms finished")
            continue
        print(f"{metric} MSE final: active {h['active_final']:.4e}  uniform {h['uniform_final']:.4e}")
        print(f"  episodes to reach the other arm's final error ({upto} {h['budget']}): uniform "
              f"{_eps(h['uniform_episodes_to_match_active'])}, active {_eps(h['active_episodes_to_match_uniform'])}")
        paired = summary[metric]["paired"]
        if paired["mean"] is not None:
            print(f"  active's final over uniform's, per seed: {paired['mean']:+.2%} ± {paired['std']:.2%} "
                  f"(active behind in {paired['active_behind']} of {paired['seeds']} seeds)")
    took = "" if summary["seconds"] is None else f"  ({summary['seconds']:.0f} s)"
    print(f"plot: {summary['plot']}\nsummary: {out / 'summary.json'}{took}")


def _eps(v: float | None) -> str:
    return "not within the budget" if v is None else f"{v:.1f}"
