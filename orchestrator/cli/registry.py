"""CLI: ``models ls|show|promote|rollback|prune``, the model registry and its ``champion`` alias.

Argument parsing and printing only: every command is one call into ``storage.models``. Nothing here
loads torch. The helpers the model commands share (``orchestrator.cli.models`` imports them) are here too.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any

from orchestrator.cli import common
from storage.catalog import Catalog
from storage.errors import CorruptCheckpointError, NotFoundError, RegistryError
from storage.jsonsafe import finite_json as strict_json  # (the name every --json of these commands uses)
from storage.models import CHAMPION, SNAPSHOT_FILE, ModelRecord, ModelRegistry, PruneResult
from storage.rows import Snapshot
from storage.strays import MODEL_ORPHANS_DIR


def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``models``."""
    models = sub.add_parser("models", help="the model registry: list, show, promote, roll back, prune")
    msub = models.add_subparsers(dest="models_command", metavar="ACTION", parser_class=common.Parser)
    msub.required = True
    p = msub.add_parser("ls", help="list registered models, champion marked")
    p.set_defaults(func=_models_ls)
    p = msub.add_parser("show", help="one model: metrics, lineage, status and reason")
    p.add_argument("version", metavar="VERSION", help="a model version (as `models ls` lists), a unique prefix "
                                                      "of one such as m000003, or champion")
    p.add_argument("--episodes", action="store_true",
                   help="list the episodes it was trained on instead, one id per line (with --json: the model "
                        "and its episodes' ids and sha256s): those of the job that trained it (a model warm-"
                        "started from another also saw what that one saw); exit 1 when they are not recorded "
                        "(pruned, or trained before models recorded them)")
    p.set_defaults(func=_models_show)
    p = msub.add_parser("promote", help="make VERSION the champion (override; still checks sha256 and split)",
                        description="Make VERSION the champion whatever the gate would say (the operator's "
                                    "override); the champion before it can be returned to with `models rollback`. "
                                    "Exit 1 when its weights fail their sha256, are pruned, or it was evaluated on "
                                    "another eval split than the pinned one.")
    p.add_argument("version", metavar="VERSION", help="a model version, a unique prefix of one such as m000003, or "
                                                      "champion (already the champion: says so, changes nothing)")
    p.set_defaults(func=_models_promote)
    p = msub.add_parser("rollback", help="return to the previous champion whose weights are intact",
                        description="Make the previous champion whose weights still match their sha256 the "
                                    "champion again (earlier ones with damaged weights, or evaluated on another "
                                    "eval split than the pinned one, are skipped); the current one is retired. "
                                    "Exit 1 when there is none to return to.")
    p.set_defaults(func=_models_rollback)
    p = msub.add_parser("prune", help="delete the weights of old retired and rejected models (rows and metrics stay)",
                        description="Delete the files of retired and rejected models, except the champion and the "
                                    "N-1 earlier champions 'models rollback' returns to (models whose weights fail "
                                    "their sha256 do not count), then, while slots remain, the latest champions "
                                    "a rollback took out of service. Candidates are never "
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


# -- helpers the model commands share ----------------------------------------------------------


def fail(message: str) -> int:
    """One line on stderr; the exit status 1."""
    print(f"activecollect: {message}", file=sys.stderr)
    return 1


def model_data_dir(args: argparse.Namespace) -> Path:
    """``--data`` of a command that reads the catalog and registry; a usage error when there is none."""
    data = Path(args.data)
    if not data.is_dir():
        raise common.UsageError(f"no data directory at {data} (give --data DIR, "
                                f"or collect and train first)")
    common.require_catalog(data)  # these commands read: they must not make a catalog where there is none
    return data


def _registry(args: argparse.Namespace, writes: bool = True) -> ModelRegistry:
    """The registry at ``--data``; a command that only reads (``writes=False``) makes no ``models/`` folder."""
    return ModelRegistry(model_data_dir(args), make_models_dir=writes)


def resolve_model(registry: ModelRegistry, version: str) -> ModelRecord:
    """The model ``version`` names, in full or by a unique prefix, or the champion for its alias ``champion``
    (no version reads so: they are ``mNNNNNN-hex``); a usage error when none does. Raises ``RegistryError``
    (exit 1, as ``eval`` without a champion) for ``champion`` while nothing has been promoted."""
    if version == CHAMPION:
        current = registry.champion()
        if current is None:
            raise RegistryError(f"no champion model yet: '{CHAMPION}' names none (train one first: "
                                "activecollect train)")
        version = current
    try:
        return registry.resolve(version)
    except NotFoundError as exc:  # (a damaged registry is not a usage error: exit 1)
        raise common.UsageError(str(exc)) from None


#: What a Spearman metric (``spearman``, ``spearman_total``, ...) that has no value shows: the rank correlation
#: is undefined over fewer than 3 eval windows, or when either side is the same on all of them (``M.spearman``).
SPEARMAN_UNDEFINED = "undefined (fewer than 3 eval windows, or the score or the error the same on all of them)"


def num(value: Any, fmt: str = ".5g", undefined: str = "undefined") -> str:
    """A number as text; ``undefined`` for NaN (a metric with no value: a Spearman over disagreements that are
    all equal, say; callers that know why say so here); '-' for anything else (not recorded)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return "-"
    return undefined if math.isnan(value) else format(value, fmt)


# -- models ------------------------------------------------------------------------------------


def _models_ls(args: argparse.Namespace) -> int:
    registry = _registry(args, writes=False)
    records, champion = registry.list(), registry.champion()
    problem = registry.weights_problem(champion) if champion is not None else None
    if problem:  # (stderr: --json output stays parseable)
        earlier = any(e.version != champion and e.rolled_back_at is None for e in registry.history())
        fix = ("`activecollect models rollback` returns to the previous champion" if earlier else
               "`activecollect models promote VERSION` serves another model (there is no earlier champion to roll "
               "back to)")
        print(f"activecollect: warning: the champion cannot be served: {problem}; {fix}, and the next retrain "
              "replaces it", file=sys.stderr)
    if args.json:
        common.print_json(strict_json({"champion": champion, "champion_problem": problem,
                                        "models": [r.to_json() for r in records]}))
        return 0
    if not records:
        print(f"no models registered in {registry.models_dir} (run: activecollect train)")
        return 0
    print(f"{'':2}{'VERSION':18} {'STATUS':17} {'H1_MSE':>10} {'H1_PSNR':>8} {'PARENT':18} CREATED")
    for r in records:
        mark = "* " if r.version == champion else "  "
        status = r.status.value + (" (pruned)" if r.pruned_at else "")
        print(f"{mark}{r.version:18} {status:17} {num(r.metrics.get('h1_mse')):>10} "
              f"{num(r.metrics.get('h1_psnr'), '.2f'):>8} {r.parent or '-':18} {r.created[:19]}")
    return 0


def _train_episodes(registry: ModelRegistry, rec: ModelRecord) -> tuple[Snapshot | None, str]:
    """The episodes ``rec`` was trained on, or None and why they cannot be listed."""
    try:
        snap = registry.snapshot(rec.version)
    except RegistryError as exc:  # pruned, or a damaged snapshot.json
        return None, f"episodes unavailable: {exc}"
    if snap is None:
        return None, (f"episodes not recorded: no {SNAPSHOT_FILE} in {rec.path} (registered before models recorded "
                      "them, or the file was removed)")
    return snap, ""


def _models_show(args: argparse.Namespace) -> int:
    registry = _registry(args, writes=False)
    rec = resolve_model(registry, args.version)
    history = [e for e in registry.history() if e.version == rec.version]
    snap, why = _train_episodes(registry, rec)
    if args.episodes and snap is None:
        return fail(f"cannot list the episodes of {rec.version}: {why}")
    if args.json:
        out = rec.to_json()
        out["champion_history"] = [vars(e) for e in history]
        out["snapshot_episode_count"] = None if snap is None else len(snap.ids)
        if args.episodes and snap is not None:
            out["snapshot_episodes"] = [{"episode_id": i, "sha256": s} for i, s in zip(snap.ids, snap.sha256s)]
        common.print_json(strict_json(out))
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
        why = SPEARMAN_UNDEFINED if key.startswith("spearman") else "undefined"
        shown = (num(value, undefined=why) if isinstance(value, (int, float)) else
                 f"[{len(value)} values]" if isinstance(value, (list, dict)) else value)
        print(f"  {key:22} {shown}")
    return 0


def _models_promote(args: argparse.Namespace) -> int:
    registry = _registry(args)
    version = resolve_model(registry, args.version).version
    try:
        decision = registry.promote(version, eval_split_hash=_current_split(args.data))
    except CorruptCheckpointError as exc:
        return fail(f"refusing to promote: {exc}")
    except RegistryError as exc:
        return fail(str(exc))
    if args.json:
        common.print_json(strict_json(decision.to_json()))
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
        version = registry.rollback(eval_split_hash=_current_split(args.data))
    except RegistryError as exc:
        return fail(f"cannot roll back: {exc}")
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
        return fail(f"cannot prune: {exc}")
    if args.json:
        common.print_json(dataclasses.asdict(result))
    else:
        print(prune_summary(result))
    return 1 if result.not_deleted else 0


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
    if result.not_deleted:
        moved += (f"; could not delete {len(result.not_deleted)} model(s)' files: "
                  + ", ".join(f"{v} ({why})" for v, why in result.not_deleted.items())
                  + " -- those still whole stay unpruned and usable")
    if not result.pruned:
        return f"nothing {'deleted' if result.not_deleted else 'to delete'} ({kept}){moved}"
    verb = "would delete" if result.dry_run else "deleted"
    what = "1 model's files" if len(result.pruned) == 1 else f"{len(result.pruned)} models' files"
    return (f"{verb} {what} ({result.freed_bytes / 2**20:.1f} MiB): "
            f"{', '.join(result.pruned)}; {kept}{moved}")


def _current_split(data: Path) -> str | None:
    """The catalog's pinned eval split hash, or None when none is pinned yet (read: no episodes/ folder made)."""
    split = Catalog(data, make_episodes_dir=False).eval_split()
    return None if split is None else split.hash
