"""CLI: ``train``, ``eval``, ``score`` and ``bench score``; the registry's ``models`` commands are in
``orchestrator.cli.registry``.

Argument parsing and printing only: every command is one call into ``uncertainty`` (training,
evaluation, scoring, the scoring benchmark) or ``orchestrator.retrain`` (the job lock and the gate).

The handlers import ``uncertainty``'s torch modules (about 2 s) when they run, so building the
parser, and every other command, does not.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orchestrator.cli import common
from orchestrator.cli.registry import SPEARMAN_UNDEFINED, fail, model_data_dir, num, resolve_model, strict_json
from orchestrator.retrainlock import EXIT_BUSY, RetrainBusyError
from orchestrator.retrainjob import quarantined_note
from storage.catalog import Catalog
from storage.episode_reader import read_episode
from storage.errors import CorruptCheckpointError, EpisodeError, NotFoundError, StorageError
from storage.models import ModelRegistry
from storage.records import Episode
from uncertainty.config import TrainConfig
from uncertainty.errors import ConfigError, UncertaintyError

if TYPE_CHECKING:
    from uncertainty.ensemble import Ensemble


def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``train``, ``eval`` and ``score`` (``orchestrator.cli.registry`` adds ``models`` after them)."""
    p = sub.add_parser("train", help="train a candidate ensemble, evaluate it, run it through the gate",
                       description="Train a candidate ensemble on every train episode, evaluate it on the pinned "
                                   "eval split and run it through the gate. By default "
                                   f"{TrainConfig.members} members, {TrainConfig.epochs} epochs, a fresh model of "
                                   f"widths {','.join(map(str, TrainConfig.widths))} and context "
                                   f"{TrainConfig.context} frames ('retrain' takes more settings). Exit "
                                   f"{EXIT_BUSY} while another job holds DATA/retrain.lock (see --wait), 1 when "
                                   "training fails (e.g. no eval split pinned).")
    p.add_argument("--members", type=common.ensemble_size, default=TrainConfig.members, metavar="K",
                   help=f"ensemble size (default {TrainConfig.members})")
    p.add_argument("--epochs", type=common.epoch_count, default=TrainConfig.epochs, metavar="N",
                   help=f"passes over the training windows, at most {common.MAX_EPOCHS} (default {TrainConfig.epochs})")
    p.add_argument("--from-champion", action="store_true", help="warm-start from the champion's weights")
    p.add_argument("--variance-head", action="store_true",
                   help="members also predict the variance of their own error (a fresh model only); eval then "
                        "reports the calibration of the total predictive variance next to the disagreement's")
    p.add_argument("--seed", type=common.non_negative_int, default=TrainConfig.seed, metavar="K",
                   help=f"seed of the initialisation and the shuffling, 0 to 2**64-1 (default {TrainConfig.seed})")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    p.add_argument("--min-improvement", type=common.fraction, default=TrainConfig.min_rel_improvement,
                   metavar="FRAC",
                   help="the gate's minimum relative improvement of h1_mse over the champion "
                        f"(default {TrainConfig.min_rel_improvement})")
    p.add_argument("--wait", action="store_true",
                   help="wait for a running retrain (DATA/retrain.lock) to finish instead of exiting "
                        f"{EXIT_BUSY} at once")
    p.set_defaults(func=_train)
    p = sub.add_parser("eval", help="evaluate a model (default: the champion) on the pinned eval split",
                       description="Evaluate a model (default: the champion) on the pinned eval split: MSE, PSNR and "
                                   "SSIM at horizons 1, 5 and 10 against the copy-last baseline, and how well its "
                                   "disagreement ranks its error (Spearman). Changes nothing; exit 1 when there is "
                                   "no champion or its weights cannot be loaded.")
    p.add_argument("version", nargs="?", metavar="VERSION",
                   help="a registered version, a unique prefix of one, or champion (the default)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    p.set_defaults(func=_eval)
    p = sub.add_parser("score", help="per-step disagreement of an episode and its most uncertain states",
                       description="The champion members' per-step disagreement on one episode (from the catalog, "
                                   "or an .mcap file) and its K most uncertain, well-separated states: what the "
                                   "active planner would ask to collect from. Changes nothing; exit 1 when there is "
                                   "no champion or the episode cannot be read (a damaged file), 2 when there is no "
                                   "such episode.")
    p.add_argument("episode", metavar="EPISODE", help="an episode id (or unique prefix) in the catalog, "
                                                      "or a path to an .mcap file")
    p.add_argument("--top", type=common.positive_int, default=5, metavar="K",
                   help="how many top states to show (default 5)")
    p.add_argument("--horizon", type=common.positive_int, default=1, metavar="H",
                   help="roll each member out H steps, at most the episode's frames minus the model's context "
                        "frames (default 1)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    p.set_defaults(func=_score)
    for p in (sub.choices["train"], sub.choices["eval"], sub.choices["score"]):
        common.add_data_arg(p)
        common.add_json_arg(p)


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    """Adds ``bench score``."""
    p = bench_sub.add_parser("score", help="frames/s of the fused ensemble and of the per-member loop")
    p.add_argument("--members", type=common.ensemble_size, default=5, metavar="K",
                   help="ensemble size, at least 2 (default 5)")
    p.add_argument("--size", type=common.positive_int, default=64, metavar="PX",
                   help="frame size in pixels, a multiple of 8 from 8 to 1024 (default 64)")
    p.add_argument("--batch", type=common.positive_int, default=48, metavar="B",
                   help="windows per forward (default 48: one 50-step episode; 1: online, one step at a time)")
    p.add_argument("--seconds", type=common.positive_float, default=10.0, metavar="S",
                   help="rough total measuring time, in seconds (default 10)")
    p.add_argument("--threads", type=common.torch_threads, default=0, metavar="N",
                   help=f"torch intra-op threads, at most {common.MAX_TORCH_THREADS} (default 0: torch's own)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    common.add_json_arg(p)
    p.set_defaults(func=_bench_score)


# -- train / eval / score ----------------------------------------------------------------------


def _train(args: argparse.Namespace) -> int:
    data = model_data_dir(args)
    try:
        cfg = TrainConfig(members=args.members, epochs=args.epochs, from_champion=args.from_champion,
                          seed=args.seed, device=args.device, min_rel_improvement=args.min_improvement,
                          variance_head=args.variance_head)
    except ConfigError as exc:
        raise common.config_error(exc, common.TRAIN_FLAGS) from None
    # torch: imported once the arguments are known good (start-up cost, not a cycle)
    from orchestrator.retrain import abandoned_note, training_job
    from uncertainty.train import train_candidate
    try:
        with training_job(data, wait=args.wait) as (catalog, registry, abandoned):
            result = train_candidate(catalog, registry, cfg)
            champion = registry.champion()
    except RetrainBusyError as exc:
        print(f"activecollect train: {exc}", file=sys.stderr)
        return EXIT_BUSY
    except (UncertaintyError, StorageError) as exc:
        return fail(f"training failed: {exc}")
    if result.quarantined:
        print(f"activecollect train: warning: {quarantined_note(result.quarantined)}", file=sys.stderr)
    if args.json:
        common.print_json(strict_json({"version": result.version, "metrics": result.metrics,
                                        "decision": result.decision.to_json(), "losses": result.losses,
                                        "champion": champion, "abandoned": abandoned,
                                        "quarantined": result.quarantined, "warnings": result.warnings}))
        return 0
    if abandoned:
        print(abandoned_note(abandoned))
    m = result.metrics
    print(f"trained {result.version}: {m.get('train_episodes')} episodes, {m.get('train_windows')} windows, "
          f"{cfg.epochs} epoch{'s' if cfg.epochs != 1 else ''} in {num(m.get('train_seconds'), '.1f')} s "
          f"(final loss {num(m.get('train_loss'))})")
    _print_eval(m)
    verdict = "promoted" if result.decision.promoted else "refused"
    print(f"gate: {verdict}: {result.decision.reason.removeprefix('promoted: ')}")  # (the gate's words)
    print(f"champion: {champion or 'none'}")
    return 0


def _print_eval(m: dict[str, Any]) -> None:
    for h in (1, 5, 10):
        if num(m.get(f"h{h}_mse")) == "undefined" and f"baseline_h{h}_mse" not in m:  # (train's NaN: no window)
            print(f"eval h{h:<2}  undefined: no eval episode is long enough for horizon {h}")
        elif f"h{h}_mse" in m:
            print(f"eval h{h:<2}  mse {num(m.get(f'h{h}_mse')):>10}  psnr {num(m.get(f'h{h}_psnr'), '.2f'):>6} dB  "
                  f"ssim {num(m.get(f'h{h}_ssim'), '.3f'):>6}  | copy-last mse "
                  f"{num(m.get(f'baseline_h{h}_mse')):>10}  psnr {num(m.get(f'baseline_h{h}_psnr'), '.2f'):>6} dB")
    print(f"calibration: spearman(disagreement, error) {num(m.get('spearman'), '.3f', SPEARMAN_UNDEFINED)}, "
          f"on {m.get('eval_episodes')} eval episodes ({m.get('eval_windows')} windows)")
    if "spearman_total" in m:
        total = num(m.get("spearman_total"), ".3f", SPEARMAN_UNDEFINED)
        print(f"calibration: spearman(total predictive variance, error) {total}, "
              f"its mean / mean error {num(m.get('h1_total_variance_ratio'), '.2f')}")


def _load(registry: ModelRegistry, version: str | None, device: str) -> Ensemble | None:
    """The ensemble of ``version`` (champion when None); prints why and returns None if it cannot."""
    if version is None and registry.champion() is None:
        fail("no champion model yet: train one first (activecollect train)")
        return None
    from uncertainty.checkpoint import load_ensemble  # torch: imported when the command runs (start-up cost)
    try:
        return load_ensemble(registry, version, None if device == "auto" else device)
    except (CorruptCheckpointError, UncertaintyError) as exc:
        fail(f"cannot load {version or 'the champion'}: {exc}")
        return None


def _eval(args: argparse.Namespace) -> int:
    data = model_data_dir(args)
    registry = ModelRegistry(data, make_models_dir=False)  # (it only reads: no models/ where none is)
    version = None if args.version is None else resolve_model(registry, args.version).version
    ensemble = _load(registry, version, args.device)
    if ensemble is None:
        return 1
    from uncertainty.train import evaluate  # torch (already loaded by _load): start-up cost, not a cycle
    try:
        metrics = evaluate(ensemble, Catalog(data, make_episodes_dir=False))  # (it only reads)
    except (UncertaintyError, StorageError) as exc:
        return fail(f"evaluation failed: {exc}")
    if args.json:
        common.print_json(strict_json({"version": ensemble.version, "metrics": metrics}))
        return 0
    print(f"model {ensemble.version} on eval split {metrics.get('eval_split_hash')}")
    _print_eval(metrics)
    return 0


def _episode(arg: str, data: Path) -> Episode:
    """The episode named by ``arg``: an .mcap path, or an id / unique id prefix in the catalog."""
    path = Path(arg)
    if path.suffix == ".mcap" or path.is_file():
        if not path.is_file():
            raise common.UsageError(f"no episode file at {path}")
        return read_episode(path)
    if not data.is_dir():
        raise common.UsageError(f"{arg!r} is not a file, and there is no data directory at {data} to look it up")
    catalog = Catalog(data, make_episodes_dir=False)  # (it only reads: no episodes/ where none is)
    try:
        return catalog.load(catalog.resolve(arg).episode_id)
    except NotFoundError as exc:
        raise common.UsageError(str(exc)) from None


def _score(args: argparse.Namespace) -> int:
    data = model_data_dir(args)  # the champion lives there: nothing to score with (or look up) without a catalog
    try:
        episode = _episode(args.episode, data)
    except EpisodeError as exc:
        return fail(f"cannot read episode {args.episode}: {exc}")
    ensemble = _load(ModelRegistry(data, make_models_dir=False), None, args.device)
    if ensemble is None:
        return 1
    size = ensemble.config.image_size
    if episode.meta.image_size != size:  # (the ensemble's own check says only the array shapes)
        return fail(f"cannot score episode {episode.meta.episode_id}: its frames are {episode.meta.image_size}px, "
                    f"the champion's {size}px: a model scores episodes of the size it trained on")
    _check_horizon(args.horizon, episode, ensemble.config.context)
    from uncertainty.score import score_episode  # torch (already loaded by _load): start-up cost, not a cycle
    try:
        score = score_episode(ensemble, episode, top_k=args.top, horizon=args.horizon)
    except UncertaintyError as exc:
        return fail(f"cannot score episode {episode.meta.episode_id}: {exc}")
    if args.json:
        common.print_json(strict_json(score.to_json()))
        return 0
    about = (f"episode {score.episode_id} ({len(score.per_step)} steps, {episode.meta.shape}) scored by "
             f"{score.model_version}")
    c = ensemble.config.context
    if len(score.per_step) < c + score.horizon:  # (--json says the same with a null per step)
        print(f"{about}: no step to score: each needs the model's {c} context frames and {score.horizon} more to "
              f"predict ({c + score.horizon} in all), the episode has {len(score.per_step)}")
        return 0
    print(f"{about}: mean disagreement {num(score.mean)} (horizon {score.horizon})")
    for s in score.top:
        agent, obj = s.state.get("agent", ()), s.state.get("object", ())
        print(f"  step {s.step:4d}  score {num(s.score):>10}  agent {_fmt_xy(agent)}  object {_fmt_xy(obj)}")
    return 0


def _check_horizon(horizon: int, episode: Episode, context: int) -> None:
    """UsageError (exit 2) for a ``--horizon`` that leaves no step of ``episode`` to score: each scored step needs
    ``context`` frames and ``horizon`` more after them."""
    longest = len(episode) - context
    if horizon > longest >= 1:
        raise common.UsageError(f"--horizon {horizon} is longer than episode {episode.meta.episode_id} allows: its "
                                f"{len(episode)} frames leave at most {longest} after the model's {context} "
                                "context frames")


def _fmt_xy(values: Any) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in values) + ")" if values else "-"


def _bench_score(args: argparse.Namespace) -> int:
    # torch: imported when the command runs (start-up cost)
    from uncertainty.benchmark import CEILING_CONV, run_score_bench
    try:
        out = run_score_bench(members=args.members, image_size=args.size, seconds=args.seconds,
                              batch=args.batch, threads=args.threads or None, device=args.device)
    except ConfigError as exc:
        raise common.config_error(exc, {"image_size": "--size", "members": "--members", "batch": "--batch",
                                        "seconds": "--seconds", "threads": "--threads"}) from None
    if args.json:
        common.print_json(strict_json(out))
        return 0
    print(f"fused {out['fused_fps']:.0f} frames/s, per-member loop {out['loop_fps']:.0f} frames/s: "
          f"{out['speedup']:.2f}x (K={args.members}, {args.size}px, batch {args.batch}, {out['device']}, "
          f"{out['threads']} threads; max |fused - loop| {out['max_abs_diff']:.1e})")
    print(f"arithmetic: {out['gflop_per_frame']:.3f} GFLOP/frame; fused {out['fused_gflops']:.0f}, loop "
          f"{out['loop_gflops']:.0f} GFLOP/s; a wide convolution ({CEILING_CONV['channels']} channels) ran "
          f"{out['ceiling_gflops']:.0f} GFLOP/s in the same run ({out['fused_share_of_ceiling']:.0%} / "
          f"{out['loop_share_of_ceiling']:.0%} of it)")
    return 0
