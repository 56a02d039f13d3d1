"""CLI: ``train``, ``eval``, ``score``, ``models ls|show|promote|rollback|prune`` and ``bench score``.

Argument parsing and printing only: every command is one call into ``uncertainty`` (training,
evaluation, scoring, the scoring benchmark) or ``storage.models`` (the registry and its gate).

The registry commands need no torch; the handlers that train, evaluate, score or
benchmark import ``uncertainty``'s torch modules (about 2 s) when they run, so
building the parser, and every other command, does not.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orchestrator.cli import common
from orchestrator.retrainlock import EXIT_BUSY, RetrainBusyError
from orchestrator.scheduler import quarantined_note
from storage.catalog import Catalog
from storage.episode_reader import read_episode
from storage.errors import CorruptCheckpointError, EpisodeError, NotFoundError, RegistryError, StorageError
from storage.models import ModelRecord, ModelRegistry, PruneResult
from storage.records import Episode
from storage.rows import Snapshot
from storage.strays import MODEL_ORPHANS_DIR
from uncertainty.config import TrainConfig
from uncertainty.errors import ConfigError, UncertaintyError

if TYPE_CHECKING:
    from uncertainty.ensemble import Ensemble

def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``train``, ``eval``, ``score`` and ``models``."""
    p = sub.add_parser("train", help="train a candidate ensemble, evaluate it, run it through the gate",
                       description="Train a candidate ensemble on every train episode, evaluate it on the pinned "
                                   "eval split and run it through the gate. By default "
                                   f"{TrainConfig.members} members, {TrainConfig.epochs} epochs, a fresh model of "
                                   f"widths {','.join(map(str, TrainConfig.widths))} and context "
                                   f"{TrainConfig.context} frames ('retrain' takes more settings).")
    p.add_argument("--members", type=common.positive_int, default=TrainConfig.members, metavar="K",
                   help=f"ensemble size (default {TrainConfig.members})")
    p.add_argument("--epochs", type=common.positive_int, default=TrainConfig.epochs, metavar="N",
                   help=f"passes over the training windows (default {TrainConfig.epochs})")
    p.add_argument("--from-champion", action="store_true", help="warm-start from the champion's weights")
    p.add_argument("--variance-head", action="store_true",
                   help="members also predict the variance of their own error (a fresh model only); eval then "
                        "reports the calibration of the total predictive variance next to the disagreement's")
    p.add_argument("--seed", type=common.non_negative_int, default=TrainConfig.seed, metavar="K",
                   help=f"seed of the initialisation and the shuffling (default {TrainConfig.seed})")
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
    p = sub.add_parser("eval", help="evaluate a model (default: the champion) on the pinned eval split")
    p.add_argument("version", nargs="?", metavar="VERSION",
                   help="a registered version or a unique prefix of one (default: the champion)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    p.set_defaults(func=_eval)
    p = sub.add_parser("score", help="per-step disagreement of an episode and its most uncertain states")
    p.add_argument("episode", metavar="EPISODE", help="an episode id (or unique prefix) in the catalog, "
                                                      "or a path to an .mcap file")
    p.add_argument("--top", type=common.positive_int, default=5, metavar="K",
                   help="how many top states to show (default 5)")
    p.add_argument("--horizon", type=common.positive_int, default=1, metavar="H",
                   help="roll each member out H steps (default 1)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    p.set_defaults(func=_score)
    for p in (sub.choices["train"], sub.choices["eval"], sub.choices["score"]):
        common.add_data_arg(p)
        common.add_json_arg(p)

    models = sub.add_parser("models", help="the model registry: list, show, promote, roll back, prune")
    msub = models.add_subparsers(dest="models_command", metavar="ACTION", parser_class=common.Parser)
    msub.required = True
    p = msub.add_parser("ls", help="list registered models, champion marked")
    p.set_defaults(func=_models_ls)
    p = msub.add_parser("show", help="one model: metrics, lineage, status and reason")
    p.add_argument("version", metavar="VERSION", help="a model version (as `models ls` lists), or a unique prefix "
                                                      "of one such as m000003")
    p.add_argument("--episodes", action="store_true",
                   help="list the episodes it was trained on instead, one id per line (with --json: the model "
                        "and its episodes' ids and sha256s): those of the job that trained it (a model warm-"
                        "started from another also saw what that one saw); exit 1 when they are not recorded "
                        "(pruned, or trained before models recorded them)")
    p.set_defaults(func=_models_show)
    p = msub.add_parser("promote", help="make VERSION the champion (override; still checks sha256 and split)")
    p.add_argument("version", metavar="VERSION", help="a model version, or a unique prefix of one such as m000003")
    p.set_defaults(func=_models_promote)
    p = msub.add_parser("rollback", help="return to the previous champion whose weights are intact")
    p.set_defaults(func=_models_rollback)
    p = msub.add_parser("prune", help="delete the weights of old retired and rejected models (rows and metrics stay)",
                        description="Delete the files of retired and rejected models, except the champion and the "
                                    "N-1 earlier champions 'models rollback' returns to (models whose weights fail their sha256 do not count), then, while slots remain, the "
                                    "latest champions a rollback took out of service. Candidates are never "
                                    "touched. The rows stay: 'models ls' and 'models show' still list every model, "
                                    "marked pruned. 'retrain --keep-models N' does the same after each retrain.")
    p.add_argument("--keep", type=common.positive_int, required=True, metavar="N",
                   help="how many models of the rollback chain keep their weights, the champion included "
                        "(1: only the champion; rollback can then go back N-1 times)")
    p.add_argument("--dry-run", action="store_true", help="say what would be deleted, delete nothing")
    p.set_defaults(func=_models_prune)
    for p in msub.choices.values():
        common.add_data_arg(p)
        common.add_json_arg(p)


# -- helpers shared by the handlers ------------------------------------------------------------


def _strict(obj: Any) -> Any:
    """Replace non-finite floats with None so that ``--json`` output is strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict(v) for v in obj]
    return obj


def _fail(message: str) -> int:
    print(f"activecollect: {message}", file=sys.stderr)
    return 1


def _data_dir(args: argparse.Namespace) -> Path:
    data = Path(args.data)
    if not data.is_dir():
        raise common.UsageError(f"no data directory at {data} (give --data DIR, "
                                f"or collect and train first)")
    common.require_catalog(data)  # these commands read: they must not make a catalog where there is none
    return data


def _registry(args: argparse.Namespace) -> ModelRegistry:
    return ModelRegistry(_data_dir(args))


def _record(registry: ModelRegistry, version: str) -> ModelRecord:
    """The model ``version`` names, in full or by a unique prefix; a usage error when none does."""
    try:
        return registry.resolve(version)
    except NotFoundError as exc:  # (a damaged registry is not a usage error: exit 1)
        raise common.UsageError(str(exc)) from None


def _num(value: Any, fmt: str = ".5g") -> str:
    return format(value, fmt) if isinstance(value, (int, float)) and not isinstance(value, bool) else "-"


# -- models ------------------------------------------------------------------------------------


def _models_ls(args: argparse.Namespace) -> int:
    registry = _registry(args)
    records, champion = registry.list(), registry.champion()
    problem = registry.weights_problem(champion) if champion is not None else None
    if problem:  # (stderr: --json output stays parseable)
        print(f"activecollect: warning: the champion cannot be served: {problem}; `activecollect models rollback` "
              "returns to the previous champion, and the next retrain replaces it", file=sys.stderr)
    if args.json:
        common.print_json(_strict({"champion": champion, "champion_problem": problem,
                                   "models": [r.to_json() for r in records]}))
        return 0
    if not records:
        print(f"no models registered in {registry.models_dir} (run: activecollect train)")
        return 0
    print(f"{'':2}{'VERSION':18} {'STATUS':17} {'H1_MSE':>10} {'H1_PSNR':>8} {'PARENT':18} CREATED")
    for r in records:
        mark = "* " if r.version == champion else "  "
        status = r.status.value + (" (pruned)" if r.pruned_at else "")
        print(f"{mark}{r.version:18} {status:17} {_num(r.metrics.get('h1_mse')):>10} "
              f"{_num(r.metrics.get('h1_psnr'), '.2f'):>8} {r.parent or '-':18} {r.created[:19]}")
    return 0


def _train_episodes(registry: ModelRegistry, rec: ModelRecord) -> tuple[Snapshot | None, str]:
    """The episodes ``rec`` was trained on, or None and why they cannot be listed."""
    try:
        snap = registry.snapshot(rec.version)
    except RegistryError as exc:  # pruned, or a damaged snapshot.json
        return None, f"episodes unavailable: {exc}"
    if snap is None:
        return None, "episodes not recorded (registered before models recorded them)"
    return snap, ""


def _models_show(args: argparse.Namespace) -> int:
    registry = _registry(args)
    rec = _record(registry, args.version)
    history = [e for e in registry.history() if e.version == rec.version]
    snap, why = _train_episodes(registry, rec)
    if args.episodes and snap is None:
        return _fail(f"cannot list the episodes of {rec.version}: {why}")
    if args.json:
        out = rec.to_json()
        out["champion_history"] = [vars(e) for e in history]
        out["snapshot_episode_count"] = None if snap is None else len(snap.ids)
        if args.episodes and snap is not None:
            out["snapshot_episodes"] = [{"episode_id": i, "sha256": s} for i, s in zip(snap.ids, snap.sha256s)]
        common.print_json(_strict(out))
        return 0
    if args.episodes and snap is not None:
        print("\n".join(snap.ids))
        return 0
    print(f"version          {rec.version}")
    print(f"status           {rec.status.value}{' (' + rec.reason + ')' if rec.reason else ''}")
    print(f"created          {rec.created}")
    print(f"parent           {rec.parent or '-'}")
    trained = f"{len(snap.ids)} episodes (--episodes lists them)" if snap is not None else why
    print(f"data snapshot    {rec.snapshot_id}: {trained}")
    print(f"eval split       {rec.eval_split_hash}")
    if rec.pruned_at:
        print(f"weights          pruned at {rec.pruned_at} (were {rec.size_bytes} bytes, sha256 {rec.weights_sha256})")
    else:
        print(f"weights          {rec.weights_path} ({rec.size_bytes} bytes, sha256 {rec.weights_sha256})")
    for e in history:
        back = f", rolled back {e.rolled_back_at}" if e.rolled_back_at else ""
        print(f"champion since   {e.promoted_at}{back}")
    print("metrics")
    for key in sorted(rec.metrics):
        value = rec.metrics[key]
        shown = (_num(value) if isinstance(value, (int, float)) else
                 f"[{len(value)} values]" if isinstance(value, (list, dict)) else value)
        print(f"  {key:22} {shown}")
    return 0


def _models_promote(args: argparse.Namespace) -> int:
    registry = _registry(args)
    version = _record(registry, args.version).version
    try:
        decision = registry.promote(version, eval_split_hash=_current_split(args.data))
    except CorruptCheckpointError as exc:
        return _fail(f"refusing to promote: {exc}")
    except RegistryError as exc:
        return _fail(str(exc))
    if args.json:
        common.print_json(_strict(decision.to_json()))
    elif decision.promoted:
        before = f" (was {decision.champion_before})" if decision.champion_before else ""
        print(f"champion is now {version}{before}")
    else:
        print(decision.reason)
    return 0


def _models_rollback(args: argparse.Namespace) -> int:
    registry = _registry(args)
    before = registry.champion()
    try:
        version = registry.rollback()
    except RegistryError as exc:
        return _fail(f"cannot roll back: {exc}")
    if args.json:
        common.print_json({"champion": version, "rolled_back_from": before})
    else:
        print(f"champion is now {version} (rolled back from {before})")
    return 0


def _models_prune(args: argparse.Namespace) -> int:
    registry = _registry(args)
    try:
        result = registry.prune(args.keep, dry_run=args.dry_run)
    except (RegistryError, OSError) as exc:
        return _fail(f"cannot prune: {exc}")
    if args.json:
        common.print_json(dataclasses.asdict(result))
        return 0
    print(prune_summary(result))
    return 0


def prune_summary(result: PruneResult) -> str:
    """One line on what a prune deleted (or would delete), what it kept, and the folders no row names it moved
    aside or could not (left in place: nothing serves them, the next prune or service sweep tries again)."""
    kept = f"kept {', '.join(result.kept)}" if result.kept else "no champion yet"
    moved = ""
    if result.orphaned:  # folders a register killed before its commit left: kept, out of the way
        verb = "would move" if result.dry_run else "moved"
        moved = (f"; {verb} {len(result.orphaned)} checkpoint folder(s) no model row names to "
                 f"{MODEL_ORPHANS_DIR}/: {', '.join(result.orphaned)}")
    if result.not_moved:
        moved += (f"; could not move {len(result.not_moved)} checkpoint folder(s) no model row names to "
                  f"{MODEL_ORPHANS_DIR}/, left where they are (unused; the next prune tries again): "
                  + ", ".join(f"{v} ({why})" for v, why in result.not_moved.items()))
    if not result.pruned:
        return f"nothing to delete ({kept}){moved}"
    verb = "would delete" if result.dry_run else "deleted"
    what = "1 model's files" if len(result.pruned) == 1 else f"{len(result.pruned)} models' files"
    return (f"{verb} {what} ({result.freed_bytes / 2**20:.1f} MiB): "
            f"{', '.join(result.pruned)}; {kept}{moved}")


def _current_split(data: Path) -> str | None:
    """The catalog's pinned eval split hash, or None when none is pinned yet."""
    split = Catalog(data).eval_split()
    return None if split is None else split.hash


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    """Adds ``bench score``."""
    p = bench_sub.add_parser("score", help="frames/s of the fused ensemble and of the per-member loop")
    p.add_argument("--members", type=common.positive_int, default=5, metavar="K", help="ensemble size (default 5)")
    p.add_argument("--size", type=common.positive_int, default=64, metavar="PX",
                   help="frame size in pixels, a multiple of 8 from 8 to 1024 (default 64)")
    p.add_argument("--batch", type=common.positive_int, default=48, metavar="B",
                   help="windows per forward (default 48: one 50-step episode; 1: online, one step at a time)")
    p.add_argument("--seconds", type=common.positive_float, default=10.0, metavar="S",
                   help="rough total measuring time, in seconds (default 10)")
    p.add_argument("--threads", type=common.positive_int, default=None, metavar="N",
                   help="torch intra-op threads (default: torch's)")
    p.add_argument("--device", type=common.torch_device, default="auto",
                   help="torch device: auto, cpu or cuda (default auto: cuda when there is one)")
    common.add_json_arg(p)
    p.set_defaults(func=_bench_score)


# -- train / eval / score ----------------------------------------------------------------------


def _train(args: argparse.Namespace) -> int:
    data = _data_dir(args)
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
        return _fail(f"training failed: {exc}")
    if result.quarantined:
        print(f"activecollect train: warning: {quarantined_note(result.quarantined)}", file=sys.stderr)
    if args.json:
        common.print_json(_strict({"version": result.version, "metrics": result.metrics,
                                   "decision": result.decision.to_json(), "losses": result.losses,
                                   "champion": champion, "abandoned": abandoned,
                                   "quarantined": result.quarantined}))
        return 0
    if abandoned:
        print(abandoned_note(abandoned))
    m = result.metrics
    print(f"trained {result.version}: {m.get('train_episodes')} episodes, {m.get('train_windows')} windows, "
          f"{cfg.epochs} epoch{'s' if cfg.epochs != 1 else ''} in {_num(m.get('train_seconds'), '.1f')} s "
          f"(final loss {_num(m.get('train_loss'))})")
    _print_eval(m)
    verdict = "promoted" if result.decision.promoted else "refused"
    print(f"gate: {verdict}: {result.decision.reason.removeprefix('promoted: ')}")  # (the gate's words)
    print(f"champion: {champion or 'none'}")
    return 0


def _print_eval(m: dict[str, Any]) -> None:
    for h in (1, 5, 10):
        if f"h{h}_mse" in m:
            print(f"eval h{h:<2}  mse {_num(m.get(f'h{h}_mse')):>10}  psnr {_num(m.get(f'h{h}_psnr'), '.2f'):>6} dB  "
                  f"ssim {_num(m.get(f'h{h}_ssim'), '.3f'):>6}  | copy-last mse "
                  f"{_num(m.get(f'baseline_h{h}_mse')):>10}  psnr {_num(m.get(f'baseline_h{h}_psnr'), '.2f'):>6} dB")
    print(f"calibration: spearman(disagreement, error) {_num(m.get('spearman'), '.3f')}, "
          f"on {m.get('eval_episodes')} eval episodes ({m.get('eval_windows')} windows)")
    if "spearman_total" in m:
        print(f"calibration: spearman(total predictive variance, error) {_num(m.get('spearman_total'), '.3f')}, "
              f"its mean / mean error {_num(m.get('h1_total_variance_ratio'), '.2f')}")


def _load(registry: ModelRegistry, version: str | None, device: str) -> Ensemble | None:
    """The ensemble of ``version`` (champion when None); prints why and returns None if it cannot."""
    if version is None and registry.champion() is None:
        _fail("no champion model yet: train one first (activecollect train)")
        return None
    from uncertainty.checkpoint import load_ensemble  # torch: imported when the command runs (start-up cost)
    try:
        return load_ensemble(registry, version, None if device == "auto" else device)
    except (CorruptCheckpointError, UncertaintyError) as exc:
        _fail(f"cannot load {version or 'the champion'}: {exc}")
        return None


def _eval(args: argparse.Namespace) -> int:
    data = _data_dir(args)
    registry = ModelRegistry(data)
    version = None if args.version is None else _record(registry, args.version).version
    ensemble = _load(registry, version, args.device)
    if ensemble is None:
        return 1
    from uncertainty.train import evaluate  # torch (already loaded by _load): start-up cost, not a cycle
    try:
        metrics = evaluate(ensemble, Catalog(data))
    except (UncertaintyError, StorageError) as exc:
        return _fail(f"evaluation failed: {exc}")
    if args.json:
        common.print_json(_strict({"version": ensemble.version, "metrics": metrics}))
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
    catalog = Catalog(data)
    try:
        return catalog.load(catalog.resolve(arg).episode_id)
    except NotFoundError as exc:
        raise common.UsageError(str(exc)) from None


def _score(args: argparse.Namespace) -> int:
    data = _data_dir(args)  # the champion lives there: nothing to score with (or look up) without a catalog
    try:
        episode = _episode(args.episode, data)
    except EpisodeError as exc:
        return _fail(f"cannot read episode {args.episode}: {exc}")
    ensemble = _load(ModelRegistry(data), None, args.device)
    if ensemble is None:
        return 1
    from uncertainty.score import score_episode  # torch (already loaded by _load): start-up cost, not a cycle
    try:
        score = score_episode(ensemble, episode, top_k=args.top, horizon=args.horizon)
    except UncertaintyError as exc:
        return _fail(f"cannot score episode {episode.meta.episode_id}: {exc}")
    if args.json:
        common.print_json(_strict(score.to_json()))
        return 0
    print(f"episode {score.episode_id} ({len(score.per_step)} steps, {episode.meta.shape}) scored by "
          f"{score.model_version}: mean disagreement {_num(score.mean)} (horizon {score.horizon})")
    for s in score.top:
        agent, obj = s.state.get("agent", ()), s.state.get("object", ())
        print(f"  step {s.step:4d}  score {_num(s.score):>10}  agent {_fmt_xy(agent)}  object {_fmt_xy(obj)}")
    return 0


def _fmt_xy(values: Any) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in values) + ")" if values else "-"


def _bench_score(args: argparse.Namespace) -> int:
    from uncertainty.benchmark import CEILING_CONV, run_score_bench  # torch: imported when the command runs (start-up cost)
    try:
        out = run_score_bench(members=args.members, image_size=args.size, seconds=args.seconds,
                              batch=args.batch, threads=args.threads, device=args.device)
    except ConfigError as exc:
        raise common.config_error(exc, {"image_size": "--size", "members": "--members", "batch": "--batch",
                                        "seconds": "--seconds", "threads": "--threads"}) from None
    if args.json:
        common.print_json(_strict(out))
        return 0
    print(f"fused {out['fused_fps']:.0f} frames/s, per-member loop {out['loop_fps']:.0f} frames/s: "
          f"{out['speedup']:.2f}x (K={args.members}, {args.size}px, batch {args.batch}, {out['device']}, "
          f"{out['threads']} threads; max |fused - loop| {out['max_abs_diff']:.1e})")
    print(f"arithmetic: {out['gflop_per_frame']:.3f} GFLOP/frame; fused {out['fused_gflops']:.0f}, loop "
          f"{out['loop_gflops']:.0f} GFLOP/s; a wide convolution ({CEILING_CONV['channels']} channels) ran "
          f"{out['ceiling_gflops']:.0f} GFLOP/s in the same run ({out['fused_share_of_ceiling']:.0%} / "
          f"{out['loop_share_of_ceiling']:.0%} of it)")
    return 0
