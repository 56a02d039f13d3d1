"""CLI: ``collect``, ``ingest``, ``eval-split create|show``, ``backup``, ``bench sim``.

``episodes ls|show|verify|quarantine|restore`` lives in ``orchestrator.cli.episodes``; ``register`` adds
it after ``collect``, where ``activecollect --help`` has always listed it."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, Mapping

from tqdm import tqdm

from orchestrator.cli import common, episodes as episodes_cli
from orchestrator.loop_catalog import eval_leftovers_warning
from orchestrator.protocol import MAX_EPISODE_STEPS, POLICIES, SHAPES, episode_problem, one_line
from orchestrator.scheduler import carry_schedule
from storage.backup import backup, check_dest
from storage.catalog import SPLITS, Catalog
from storage.database import DB_NAME
from storage.episode_reader import inspect_episode, read_file
from storage.errors import (BackupError, CatalogError, EpisodeError, OtherSplitError, StorageError,
                            StorageUnavailableError)
from storage.records import MAX_FRAME_SIZE, MIN_FRAME_SIZE, TRAINABLE_SIZES, trainable_size
from workers import simbench
from workers.collect import (EVAL_POLICY, EvalSplitConflict, check_eval_split, collect_episode, collect_plan,
                             create_eval_split, eval_split_plan, plan_replays)


def rendered_size(text: str) -> int:
    """A frame size the simulator renders (``bench sim``: nothing is kept, so no model need train on it)."""
    value = common.positive_int(text)
    if not MIN_FRAME_SIZE <= value <= MAX_FRAME_SIZE:
        raise argparse.ArgumentTypeError(f"expected a size in pixels in [{MIN_FRAME_SIZE}, {MAX_FRAME_SIZE}], "
                                         f"found {value}")
    return value


#: ``eval-split create``'s flag for each parameter of a pinned split (``workers.collect.eval_split_params``).
EVAL_SPLIT_FLAGS = {"episodes": "--episodes", "seed": "--seed", "steps": "--steps", "image_size": "--size"}


def eval_split_refusal(data: Path, exc: EvalSplitConflict, flags: dict[str, str], command: str,
                       asks: str) -> common.UsageError:
    """The usage error for a pinned split made with other parameters: every flag (of ``flags``, the
    ``command``'s flag for each split parameter) that must change, with the values that would keep
    it, and what the command asked for (``asks``: "this run asks for" ...)."""
    matchable = {k: v for k, v in exc.held.items() if k in flags and v is not None and _flag_can_give(k, v)}
    other = [_made_with(k, v) for k, v in exc.held.items() if k not in matchable]
    if other:  # something no flag of this command can match (or no longer accepts: 12 px, 2 steps)
        return common.UsageError(f"{data}'s evaluation split was made with {', '.join(other)}, which "
                                 f"{command} does not make: give another --data")
    made = " ".join(f"{flags[k]} {v}" for k, v in matchable.items())
    asked = " ".join(f"{flags[k]} {exc.asked[k]}" for k in matchable)
    return common.UsageError(f"{data}'s evaluation split was made with {made} ({asks} {asked}): give those, "
                             "or another --data")


def refuse_other_settings(data: Path, flags: dict[str, str], command: str, asks: str, size_flag: str,
                          **settings: Any) -> str | None:
    """Before anything is collected or made: a usage error naming every flag to change when ``data``
    holds an eval split made with other ``settings`` (``check_eval_split``'s arguments), or episodes of
    another frame size. The pinned split's hash when it stays; None when none is pinned yet."""
    if not (Path(data) / DB_NAME).is_file():
        return None
    try:
        pinned = check_eval_split(Catalog(data, make_episodes_dir=False), **settings)  # (a refusal makes nothing)
    except EvalSplitConflict as exc:
        raise eval_split_refusal(data, exc, flags, command, asks) from None
    common.require_frame_size(data, settings["image_size"], size_flag)
    return pinned


def _flag_can_give(key: str, value: Any) -> bool:
    """Whether the flag of a split parameter accepts ``value`` today (older versions pinned any size and length)."""
    if key == "image_size":
        return common.trainable_size(value)
    if key == "steps":
        return common.MIN_EPISODE_STEPS <= value <= MAX_EPISODE_STEPS
    return True


def _made_with(key: str, value: Any) -> str:
    if key == "palette":
        return "a palette" if value else "the default colours"
    if key == "random_physics":
        return "random physics" if value else "the default physics"
    if value is None:
        return f"another {key.replace('_', ' ')} (not recorded)"
    return f"{key.replace('_', ' ')} {value}"


def make_eval_split(catalog: Catalog, episodes: int, seed: int, steps: int, image_size: int,
                    random_physics: bool = False, palette: Mapping[str, tuple[int, int, int]] | None = None) -> str:
    """The loops' ``create_eval_split`` (``run``'s and ``bench loop``'s), positional: the simulator's split."""
    return create_eval_split(catalog, episodes=episodes, seed=seed, steps=steps, image_size=image_size,
                             random_physics=random_physics, palette=palette)


def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``collect``, ``episodes`` (``orchestrator.cli.episodes``), ``ingest``, ``eval-split`` and ``backup``."""
    p = sub.add_parser("collect", help="record pushing episodes locally and index them",
                       description="Record pushing episodes with the simulator on this machine and index them as "
                                   "train episodes in the catalog at --data (made when missing). Refused (exit 2) "
                                   "before anything is recorded when --size differs from the frame size the "
                                   "catalog holds, or when --seed would record eval episodes again.")
    p.add_argument("--episodes", type=common.episode_count, default=10, metavar="N",
                   help=f"how many, at most {common.MAX_COLLECT_EPISODES} (default 10)")
    p.add_argument("--shape", choices=(*SHAPES, "all"), default="all",
                   help="object shape; 'all' takes the shapes in turn (default)")
    p.add_argument("--policy", choices=POLICIES, default="push", help="collection policy (default push)")
    p.add_argument("--size", type=common.trainable_image_size, default=64, metavar="PX",
                   help=f"frame size in pixels, {TRAINABLE_SIZES} (default 64)")
    p.add_argument("--steps", type=common.episode_steps, default=50, metavar="T",
                   help=f"steps per episode, {common.MIN_EPISODE_STEPS}..{common.MAX_EPISODE_STEPS} (default 50)")
    p.add_argument("--seed", type=common.non_negative_int, default=0, metavar="K",
                   help="seed of start states and policies (default 0)")
    common.add_data_arg(p)
    common.add_json_arg(p)
    p.set_defaults(func=_collect)

    episodes_cli.register(sub)  # between collect and ingest in --help's list

    p = sub.add_parser("ingest", help="verify and index MCAP episode files collected elsewhere",
                       description="Verify MCAP episode files collected elsewhere and index them at --data (each is "
                                   "copied into DATA/episodes/). A bad file is refused with its reason and the rest "
                                   "go on: exit 1 when any was refused. The bytes of an episode already indexed "
                                   "repair its missing, damaged or quarantined file. Where --data holds no "
                                   "catalog, the first good file starts one (said on stderr).")
    p.add_argument("paths", nargs="+", type=common.given_path, metavar="PATH",
                   help="MCAP files, or directories of them")
    p.add_argument("--split", choices=SPLITS, default="train",
                   help="split to index them in (default train); eval episodes are neither trained nor evaluated "
                        "on until `eval-split pin` pins them")
    common.add_data_arg(p)
    common.add_json_arg(p)
    p.set_defaults(func=_ingest)

    split = sub.add_parser("eval-split", help="the pinned evaluation split: create, pin, show")
    ssub = split.add_subparsers(dest="eval_split_command", metavar="ACTION", parser_class=common.Parser)
    ssub.required = True
    p = ssub.add_parser("create", help="collect the evaluation episodes (push policy, all shapes) and pin them",
                        description="Collect the evaluation episodes (push policy, the shapes in turn, from --seed) "
                                    "and pin them: every model of --data is measured on them and none trains on "
                                    "them. A pinned split is never replaced: the same settings again change "
                                    "nothing, other settings exit 2 naming the flags to give, before anything is "
                                    "collected.")
    p.add_argument("--episodes", type=common.episode_count, default=24, metavar="N",
                   help=f"evaluation episodes, at most {common.MAX_COLLECT_EPISODES}; shapes take turns (default 24)")
    p.add_argument("--seed", type=common.non_negative_int, default=1234, metavar="K",
                   help="seed of their start states and policies (default 1234, as `run --eval-seed`)")
    p.add_argument("--size", type=common.trainable_image_size, default=64, metavar="PX",
                   help=f"frame size in pixels, {TRAINABLE_SIZES}; models of this directory predict frames of "
                        "this size (default 64)")
    p.add_argument("--steps", type=common.episode_steps, default=50, metavar="T",
                   help=f"steps per episode, {common.MIN_EPISODE_STEPS}..{common.MAX_EPISODE_STEPS} (default 50)")
    p.set_defaults(func=_eval_split_create)
    p = ssub.add_parser("pin", help="pin the eval split to episodes ingested with --split eval",
                        description="Pin the evaluation split to episodes collected elsewhere and indexed with "
                                    "`activecollect ingest PATH --split eval` (eval-split create collects its own "
                                    "instead). Once pinned, the split never changes: every model of the directory "
                                    "is measured on it and none trains on it. Pinning the same episodes again "
                                    "is a no-op.")
    p.add_argument("episode_ids", nargs="*", metavar="EPISODE",
                   help="episode ids or unique prefixes, all of split eval (default: every eval episode indexed "
                        "and not quarantined)")
    p.set_defaults(func=_eval_split_pin)
    p = ssub.add_parser("show", help="the pinned split's hash and episodes",
                        description="The pinned split's hash, when it was made and its episodes per shape; exit 1 "
                                    "when none is pinned.")
    p.set_defaults(func=_eval_split_show)
    for p in ssub.choices.values():
        common.add_data_arg(p)
        common.add_json_arg(p)

    p = sub.add_parser(
        "backup", help="copy the data directory to a new directory, consistently, while the service runs",
        description="Copy the catalog, queue and model registry (one SQLite snapshot, taken while "
                    "writers go on), every indexed episode and every kept checkpoint to DEST, checking "
                    "each file's sha256 as it is read. DEST appears only once complete (a backup killed midway leaves "
                    "a hidden folder and lock file beside it, which the next backup to DEST deletes). One backup "
                    "to DEST at a time: a second one exits 1 at once naming the first's pid. Restore: stop "
                    "the service and serve from DEST (--data DEST), or move it into place. Exit 1 when "
                    "a file could not be copied intact (the rest is backed up and the files are named).")
    p.add_argument("dest", type=common.given_path, metavar="DEST",
                   help="a new (or empty) directory outside the data directory, ideally on another disk")
    common.add_data_arg(p)
    common.add_json_arg(p)
    p.set_defaults(func=_backup)


def register_bench(bench_sub: argparse._SubParsersAction) -> None:
    """Adds ``bench sim``."""
    p = bench_sub.add_parser("sim", help="recorded frames per second of one process (simulate + render + write MCAP)")
    p.add_argument("--size", type=rendered_size, default=96, metavar="PX",
                   help=f"frame size in pixels, {MIN_FRAME_SIZE}..{MAX_FRAME_SIZE} (default 96)")
    p.add_argument("--seconds", type=common.positive_float, default=5.0, metavar="S",
                   help="how long to measure, in seconds (default 5)")
    common.add_json_arg(p)
    p.set_defaults(func=_bench_sim)


# -- helpers -----------------------------------------------------------------------------------


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


# -- collect -----------------------------------------------------------------------------------


def _collect(args: argparse.Namespace) -> int:
    common.require_frame_size(args.data, args.size, "--size")
    plan = collect_plan(args.episodes, args.seed, None if args.shape == "all" else args.shape)
    _refuse_replays(args.data, plan, args.policy, args.size, "train", args.seed)
    cat = Catalog(args.data)
    results, frames, size, ep = [], 0, 0, None
    started = time.perf_counter()
    try:
        with tqdm(total=args.episodes, unit="ep", desc="collect", file=sys.stderr, disable=None) as bar:
            for policy_seed, start in plan:
                ep = None
                ep = collect_episode(start_state=start, policy=args.policy, seed=policy_seed,
                                     steps=args.steps, image_size=args.size)
                res = cat.add_episode(ep)
                results.append(res)
                frames += len(ep)
                size += res.path.stat().st_size
                bar.update(1)
    except KeyboardInterrupt:  # what is kept, and why the same command would now be refused
        in_hand = ep is not None and ep.meta.episode_id not in {r.episode_id for r in results}
        kept = len(results) + bool(in_hand and cat.find(ep.meta.episode_id))
        again = f"; --seed {args.seed} would record them again: give another --seed for more" if kept else ""
        print(one_line(f"activecollect: interrupted: {kept} of the {args.episodes} episodes asked for are indexed "
                       f"in {cat.data_dir} and kept{again}"), file=sys.stderr)
        return 130
    seconds = time.perf_counter() - started
    out = {"episodes": [r.episode_id for r in results], "frames": frames, "bytes": size,
           "seconds": round(seconds, 3), "data_dir": str(cat.data_dir),
           "episodes_dir": str(cat.episodes_dir), "catalog": str(cat.db_path), "total_episodes": cat.count()}
    if args.json:
        common.print_json(out)
        return 0
    print(f"collected {len(results)} episodes ({frames} frames, {_megabytes(size)}) in {seconds:.1f} s")
    print(f"episodes: {cat.episodes_dir}/<date>/<episode_id>.mcap")
    print(f"catalog:  {cat.db_path} ({out['total_episodes']} episodes)")
    return 0


def refuse_eval_replays(data: Path, episodes: int, seed: int, size: int, flag: str = "--seed") -> None:
    """Before an eval split is made (``eval-split create``, ``run``): a usage error naming ``flag`` when train
    episodes already record some of its episodes (``_refuse_replays``)."""
    _refuse_replays(data, eval_split_plan(episodes, seed), EVAL_POLICY, size, "eval", seed, flag)


def _refuse_replays(data: Path, plan: list, policy: str, size: int, split: str, seed: int,
                    flag: str = "--seed") -> None:
    """Before anything is collected: a usage error when episodes of ``plan`` (drawn from ``seed``, given as
    ``flag``), indexed in ``split``, would replay episodes of the other split (the eval split's seed and policy
    make its episodes again, under new ids), which the catalog would refuse one by one (``plan_replays``)."""
    if not (Path(data) / DB_NAME).is_file():
        return
    cat = Catalog(data, make_episodes_dir=False)  # (a refusal makes nothing)
    if split == "train" and (again := plan_replays(cat, plan, policy, size, split, within=True)):
        raise common.UsageError(f"--seed {seed} would record train episode {again[min(again)]} again ({len(again)} "
                                f"of the {len(plan)} episodes asked for are in {data} already: the same --seed, "
                                "--shape and --policy record the same episodes); give another --seed")
    replayed = plan_replays(cat, plan, policy, size, split)
    if not replayed:
        return
    other, many = replayed[min(replayed)], f"{len(replayed)} of the {len(plan)} episodes asked for"
    if split == "train":
        raise common.UsageError(f"--seed {seed} would record eval episode {other} again ({many} replay eval "
                                f"episodes of {data}): training on them would leak the eval split; give another "
                                "--seed")
    raise common.UsageError(f"{flag} {seed} would record train episode {other} again as an eval episode ({many} "
                            f"replay train episodes of {data}): models trained on those would be measured on their "
                            f"own training data; give another {flag}")


# -- ingest ------------------------------------------------------------------------------------


def _expand(paths: list[Path]) -> list[Path]:
    files = []
    for path in paths:
        if path.is_dir():
            found = sorted(p for p in path.rglob("*.mcap") if not p.name.startswith("."))
            if not found:
                raise common.UsageError(f"no .mcap files under {path}")
            files.extend(found)
        elif path.exists():
            files.append(path)
        else:
            raise common.UsageError(f"no such file or directory: {path}")
    return files


def _would_start_a_catalog(path: Path) -> None:
    """The checks of ``Catalog.ingest_file`` that a new catalog would make of its first file, without making one
    (a misspelt --data and a bad file must leave nothing behind); the ``StorageError`` it would raise."""
    info = inspect_episode(read_file(path, CatalogError), name=str(path))
    refusal = episode_problem(info.meta) or ("" if trainable_size(info.meta.image_size) else
                                             f"{info.meta.image_size}px frames: no model trains on that size "
                                             f"({TRAINABLE_SIZES})")
    if refusal:
        raise EpisodeError(f"{path}: {refusal}")


def _ingest(args: argparse.Namespace) -> int:
    files = _expand(args.paths)
    cat = Catalog(args.data) if (Path(args.data) / DB_NAME).is_file() else None  # made with the first good file
    if args.split == "eval" and cat is not None and cat.eval_split() is not None:
        print(f"activecollect: warning: {args.data} has its eval split pinned already (fixed for good): episodes "
              "ingested as eval now are kept, but nothing trains or evaluates on them", file=sys.stderr)
    report: list[dict] = []
    interrupted = False
    try:
        cat = _ingest_each(args, files, cat, report)
    except KeyboardInterrupt:  # (each file indexed is committed before the next is read)
        indexed, at, interrupted = sum(r["ok"] for r in report), min(len(report), len(files) - 1), True
        print(one_line(f"activecollect: interrupted at file {at + 1} of {len(files)} ({files[at]}): the {indexed} "
                       "indexed before it are kept; run it again to index the rest (files already indexed are "
                       "not indexed twice)"), file=sys.stderr)
    refused = sum(not r["ok"] for r in report)
    if args.json:  # (interrupted too: what was done so far, where a script reading it got nothing)
        common.print_json({"ingested": len(report) - refused, "refused": refused, "files": report,
                           "interrupted": interrupted})
    elif not interrupted:
        where = cat.db_path if cat is not None else f"{Path(args.data) / DB_NAME} (not made: nothing to index)"
        print(f"{len(report) - refused} of {len(report)} files indexed in {where}")
    return 130 if interrupted else 1 if refused else 0


def _ingest_each(args: argparse.Namespace, files: list[Path], cat: Catalog | None,
                 report: list[dict]) -> Catalog | None:
    """Ingests each of ``files`` into ``cat`` (made with the first good file when None), appending to ``report``
    as each is done; the catalog (None when none was made)."""
    for path in files:
        try:
            if cat is None:
                _would_start_a_catalog(path)
                cat = Catalog(args.data)
                print(f"activecollect: no catalog at {args.data}: started a new one (a misspelt --data? the "
                      "files are indexed there)", file=sys.stderr)
            res = cat.ingest_file(path, split=args.split, admit=episode_problem)
        except StorageError as exc:
            report.append({"path": str(path), "ok": False, "error": f"{type(exc).__name__}: {exc}"})
            if isinstance(exc, StorageUnavailableError):  # not the file's fault: a full disk, a busy catalog
                print(one_line(f"activecollect: cannot store {path} now (nothing changed; run it again): {exc}"),
                      file=sys.stderr)
            else:
                hint = f" (give --split {exc.split})" if isinstance(exc, OtherSplitError) else ""
                print(one_line(f"activecollect: refused {path}: {exc}{hint}"), file=sys.stderr)
            continue
        report.append({"path": str(path), "ok": True, "episode_id": res.episode_id,
                       "duplicate": res.duplicate, "restored": res.restored, "stored": str(res.path)})
        if not args.json:
            state = "restored" if res.restored else "already indexed" if res.duplicate else "ingested"
            print(f"{state} {res.episode_id} from {path}")
    return cat


# -- eval split --------------------------------------------------------------------------------


def _eval_split_create(args: argparse.Namespace) -> int:
    settings = dict(episodes=args.episodes, seed=args.seed, steps=args.steps, image_size=args.size)
    # a pinned split is never replaced: checked before collecting
    pinned = refuse_other_settings(args.data, EVAL_SPLIT_FLAGS, "eval-split create", "asked for", "--size", **settings)
    if pinned is None:
        refuse_eval_replays(args.data, args.episodes, args.seed, args.size)
    cat = Catalog(args.data)
    if pinned is None:
        print(f"collecting {args.episodes} evaluation episodes ({args.steps} steps, {args.size}px) ...",
              file=sys.stderr)
    try:
        digest = create_eval_split(cat, **settings)
    except EvalSplitConflict as exc:  # pinned by another process since the check
        raise eval_split_refusal(args.data, exc, EVAL_SPLIT_FLAGS, "eval-split create", "asked for") from None
    except CatalogError as exc:
        print(f"activecollect: {exc}", file=sys.stderr)
        return 1
    split = cat.eval_split()
    n = len(split.ids) if split else 0
    if args.json:
        common.print_json({"hash": digest, "episodes": n, "made": pinned is None})
    else:
        print(f"eval split {'pinned' if pinned is None else 'already pinned, with these settings'}: {n} episodes, "
              f"hash {digest}")
    if leftovers := eval_leftovers_warning(cat):
        print(f"activecollect: warning: {leftovers}", file=sys.stderr)
    return 0


def _eval_split_pin(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args, writes=True)
    if args.episode_ids:
        rows = [episodes_cli.resolve(cat, i) for i in args.episode_ids]
        ids = [r.episode_id for r in rows]
    else:
        ids = cat.snapshot("eval").ids
        if not ids:
            raise common.UsageError(f"no eval episodes to pin in {cat.data_dir}: index them with `activecollect "
                                    "ingest PATH --split eval`, or collect a split with `eval-split create`")
    try:
        digest = cat.pin_eval_split(ids, params={"image_size": cat.frame_size(), "pinned": "ingested episodes"})
    except CatalogError as exc:
        print(one_line(f"activecollect: {exc}"), file=sys.stderr)
        return 1
    split = cat.eval_split()
    if args.json:
        common.print_json({"hash": digest, "episodes": len(split.ids)})
    else:
        print(f"eval split pinned: {len(split.ids)} episodes, hash {digest}")
    return 0


def _eval_split_show(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args)
    split = cat.eval_split()
    if split is None:
        waiting = len(cat.snapshot("eval").ids)
        hint = (f"{waiting} eval episodes are indexed, not pinned: an `eval-split create` that was interrupted "
                "finishes when run again with the same flags (pinning what it left would fix a partial split for "
                "good); pin episodes ingested with --split eval with activecollect eval-split pin" if waiting
                else "create one: activecollect eval-split create")
        print(f"activecollect: no eval split is pinned in {cat.data_dir} ({hint})", file=sys.stderr)
        return 1
    if args.json:
        common.print_json({"hash": split.hash, "created": split.created, "params": split.params,
                           "episodes": split.ids})
        return 0
    shapes: dict[str, int] = {}
    for i in split.ids:
        shape = cat.get(i).shape
        shapes[shape] = shapes.get(shape, 0) + 1
    print(f"hash      {split.hash}")
    print(f"created   {split.created}")
    print(f"episodes  {len(split.ids)} ({', '.join(f'{k}: {v}' for k, v in sorted(shapes.items()))})")
    return 0


# -- backup ------------------------------------------------------------------------------------


def _backup(args: argparse.Namespace) -> int:
    common.require_catalog(args.data)
    try:
        check_dest(args.data, args.dest)
    except BackupError as exc:
        raise common.UsageError(str(exc)) from None
    with tqdm(unit="file", desc="backup", file=sys.stderr, disable=None) as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)
        try:
            result = backup(args.data, args.dest, progress=progress, carry=carry_schedule)
        except BackupError as exc:
            bar.close()
            print(f"activecollect: backup failed, nothing written at {args.dest}: {exc}", file=sys.stderr)
            return 1
    for path in result.swept:
        print(one_line(f"activecollect: deleted {path}, left by a backup to {result.dest} that was killed midway"),
              file=sys.stderr)
    if args.json:
        common.print_json({"dest": str(result.dest), "episodes": result.episodes, "models": result.models,
                           "bytes": result.bytes, "seconds": result.seconds, "problems": result.problems,
                           "swept": [str(p) for p in result.swept]})
    else:
        print(f"backed up {result.episodes} episodes and {result.models} checkpoints "
              f"({_megabytes(result.bytes)}) to {result.dest} in {result.seconds:.1f} s")
        for line in result.problems:
            print(f"NOT COPIED {line}")
    if result.problems:
        print(f"activecollect: {len(result.problems)} file(s) could not be copied intact (above); "
              "see `activecollect episodes verify`", file=sys.stderr)
    return 1 if result.problems else 0


# -- bench -------------------------------------------------------------------------------------


def _bench_sim(args: argparse.Namespace) -> int:
    result = simbench.run_sim_bench(image_size=args.size, seconds=args.seconds)
    if args.json:
        common.print_json(result)
    else:
        for key, value in result.items():
            print(f"{key:<24} {value}")
    return 0
