"""CLI: ``episodes ls|show|verify|quarantine|restore``, the episode catalog (added by
``orchestrator.cli.collect.register``, after ``collect``)."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from tqdm import tqdm

from orchestrator.cli import common
from orchestrator.protocol import SHAPES, one_line
from storage import quarantine as quarantines
from storage.catalog import ORPHANS_DIR, SPLITS, Catalog, EpisodeRow
from storage.database import QUARANTINE_DIR
from storage.errors import DAMAGED_EPISODE_ERRORS, CatalogError, NotFoundError, StorageError


def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``episodes``."""
    episodes = sub.add_parser("episodes", help="the episode catalog: list, show, verify, quarantine, restore")
    esub = episodes.add_subparsers(dest="episodes_command", metavar="ACTION", parser_class=common.Parser)
    esub.required = True
    p = esub.add_parser("ls", help="list indexed episodes, oldest first")
    p.add_argument("--split", choices=SPLITS, help="only episodes of this split (default: all)")
    p.add_argument("--shape", choices=SHAPES, help="only episodes of this object shape (default: all)")
    p.add_argument("--limit", type=common.positive_int, metavar="N", help="only the N newest")
    p.add_argument("--quarantined", action="store_true",
                   help="only the episodes taken out of training, with where their files are kept and the space "
                        "they take")
    p.set_defaults(func=_episodes_ls)
    p = esub.add_parser("show", help="one episode: catalog row and provenance")
    p.add_argument("episode_id", metavar="ID", help="episode id or a unique prefix of it")
    p.set_defaults(func=_episodes_show)
    p = esub.add_parser("verify", help="re-hash and re-verify episode files (all when no ID); exit 1 if any is bad",
                        description="Re-hash and re-verify the files of the episodes named (all not quarantined "
                                    "when none is). Exit 1 when any is bad (missing, other bytes than indexed, "
                                    "unreadable); with --quarantine the bad train episodes are also taken out "
                                    "of training (exit 0 when that took care of every bad one).")
    p.add_argument("episode_ids", nargs="*", metavar="ID",
                   help="episode ids or unique prefixes (default: every episode not quarantined)")
    p.add_argument("--quarantine", action="store_true",
                   help="quarantine the bad train episodes found (as a retrain would)")
    p.set_defaults(func=_episodes_verify)
    p = esub.add_parser(
        "quarantine", help="take episodes out of training; their files move to DATA/quarantine/",
        description="Take episodes out of training: the catalog keeps their rows, their files move to "
                    "DATA/quarantine/<day>/ and no snapshot includes them. Retrains do this themselves for "
                    "files found missing or damaged. Episodes of the pinned eval split cannot be "
                    "quarantined. `episodes restore`, or ingesting the same bytes again, brings them back.")
    p.add_argument("episode_ids", nargs="+", metavar="ID", help="episode ids or unique prefixes")
    p.add_argument("--reason", required=True, help="why (kept with the episode, one line)")
    p.set_defaults(func=_episodes_quarantine)
    p = esub.add_parser("restore", help="put quarantined episodes back into training",
                        description="Move quarantined episodes' files back (when they still hold the bytes "
                                    "indexed) and let training use them again. For one whose file is gone or "
                                    "damaged, ingest its original bytes again instead (`activecollect ingest`). "
                                    "One already in training is left as it is and said to be (exit 0), as "
                                    "`quarantine` leaves one already quarantined.")
    p.add_argument("episode_ids", nargs="*", metavar="ID", help="episode ids or unique prefixes")
    p.add_argument("--all", action="store_true", help="every quarantined episode (e.g. after a disk came back)")
    p.set_defaults(func=_episodes_restore)
    for p in esub.choices.values():
        common.add_data_arg(p)
        common.add_json_arg(p)


def resolve(cat: Catalog, episode_id: str) -> EpisodeRow:
    """The episode ``episode_id`` names (an id or a unique prefix); a usage error (exit 2) when none does."""
    try:
        return cat.resolve(episode_id)
    except NotFoundError as exc:  # (a damaged catalog is not a usage error: exit 1)
        raise common.UsageError(str(exc)) from None


def resolve_all(cat: Catalog, episode_ids: list[str]) -> list[EpisodeRow]:
    """The episodes ``episode_ids`` name (``resolve``), each once in the order first named: an id given twice, or
    as itself and as a prefix, is one episode (a second restore of it would say it is not quarantined)."""
    rows = {}
    for i in episode_ids:
        row = resolve(cat, i)
        rows.setdefault(row.episode_id, row)
    return list(rows.values())


def _episodes_ls(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args)
    quarantined = True if args.quarantined else None
    rows = cat.list(split=args.split, shape=args.shape, limit=args.limit, newest_first=args.limit is not None,
                    quarantined=quarantined)
    if args.limit is not None:
        rows.reverse()
    kept = {r.episode_id: _kept(cat, r) for r in rows if r.quarantined}
    if args.json:
        out = [r.to_json() for r in rows]
        for entry in out:
            if entry["episode_id"] in kept:
                path, size = kept[entry["episode_id"]]
                entry.update(kept=str(path) if path else None, kept_bytes=size)
        common.print_json(out)
        return 0
    if not rows:
        print(f"no {'quarantined ' if args.quarantined else ''}episodes in {cat.data_dir}")
        return 0
    print(f"{'EPISODE':<32}  {'SHAPE':<5} {'FRAMES':>6}  {'SPLIT':<5}  {'CREATED':<19}  {'SIZE':>8}  REQUEST")
    for r in rows:
        print(f"{r.episode_id:<32}  {r.shape:<5} {r.frames:>6}  {r.split:<5}  {r.created[:19]:<19}  "
              f"{r.size_bytes / 1e3:>6.0f}KB  {r.request_id or '-'}")
        if r.quarantined:
            path, size = kept[r.episode_id]
            print(f"  quarantined: {r.quarantined}")
            print(f"  kept: {path} ({size / 1e3:.0f}KB)" if path else
                  "  kept: no file (only an ingest of its original bytes brings it back)")
    held = cat.count(quarantined=True)
    shown = sum(size for _, size in kept.values())
    space = f"; the files of those shown take {shown / 1e6:.1f} MB in {cat.data_dir / QUARANTINE_DIR}" if kept else ""
    print(f"{len(rows)} of {cat.count()} episodes" + (f" ({held} quarantined)" if held else "") + space)
    return 0


def _kept(cat: Catalog, row: EpisodeRow) -> tuple[Path | None, int]:
    """Where a quarantined episode's file is kept, and its size (None, 0 when none is)."""
    path = cat.kept_file(row)
    try:
        return path, path.stat().st_size if path is not None else 0
    except FileNotFoundError:  # restored or deleted since
        return None, 0


def _episodes_show(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args)
    row = resolve(cat, args.episode_id)
    out: dict[str, Any] = {**row.to_json(), "meta": vars(cat.meta(row.episode_id))}
    if args.json:
        common.print_json(out)
        return 0
    text = {**{k: v for k, v in out.items() if k != "meta"}, **out["meta"]}
    text["ingested"] = datetime.fromtimestamp(row.ingested, timezone.utc).isoformat(timespec="seconds")
    for key, value in text.items():
        shown = json.dumps(value, sort_keys=True) if isinstance(value, (dict, list)) else value
        print(f"{key:<18} {shown if shown != '' else '-'}")
    return 0


def _episodes_verify(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args, writes=args.quarantine)
    rows = resolve_all(cat, args.episode_ids) if args.episode_ids else cat.list(quarantined=False)
    report = []
    for row in tqdm(rows, unit="ep", desc="verify", file=sys.stderr, disable=None):
        entry = {"episode_id": row.episode_id, "ok": True, "error": "", "quarantined": bool(row.quarantined)}
        try:
            cat.verify(row.episode_id)
        except StorageError as exc:
            entry.update(ok=False, error=f"{type(exc).__name__}: {exc}")
            if args.quarantine and not row.quarantined and isinstance(exc, DAMAGED_EPISODE_ERRORS):
                entry["quarantined"] = _quarantine_bad(cat, row, exc)
        report.append(entry)
    bad = [r for r in report if not r["ok"]]
    unresolved = [r for r in bad if not r["quarantined"]]
    strays = cat.strays() if not args.episode_ids else None
    stray_paths = [str(p) for p in (strays.staging + strays.unindexed)] if strays else []
    if args.json:
        common.print_json({"checked": len(report), "bad": len(bad), "episodes": report, "strays": stray_paths,
                           "quarantined": cat.count(quarantined=True)})
    else:
        for r in bad:
            print(f"BAD {r['episode_id']}: {r['error']}" + (" (quarantined)" if r["quarantined"] else ""))
        held = cat.count(quarantined=True)
        print(f"verified {len(report)} episodes: {len(report) - len(bad)} ok, {len(bad)} bad"
              + (f"; {held} quarantined in all (`episodes ls --quarantined`)" if held else ""))
        if stray_paths:  # never acknowledged, so not an error; `serve` moves them aside when it starts
            print(f"{len(stray_paths)} file(s) left by a crashed ingest, not in the catalog "
                  f"(`serve` moves them to {ORPHANS_DIR}/ at start-up):")
            for path in stray_paths:
                print(f"  {path}")
    return 1 if (unresolved if args.quarantine else bad) else 0


def _quarantine_bad(cat: Catalog, row: EpisodeRow, exc: StorageError) -> bool:
    """Quarantines a bad episode ``verify`` found; False (with a line on stderr) when it cannot be."""
    try:  # (a repair that came in since it was read wins: then it is not quarantined)
        kept = cat.quarantine(row.episode_id, f"found by episodes verify: {exc}", only_if_damaged=True)
        return bool(kept.quarantined)
    except CatalogError as why:
        print(one_line(f"activecollect: cannot quarantine {row.episode_id}: {why}"), file=sys.stderr)
        return False


def _episodes_quarantine(args: argparse.Namespace) -> int:
    cat = common.existing_catalog(args, writes=True)
    if not args.reason.strip():
        raise common.UsageError("--reason must say why")
    rows = resolve_all(cat, args.episode_ids)  # all known before any changes
    split = cat.eval_split()
    for row in rows:
        if split is not None and row.episode_id in split.ids:  # (one pinned meanwhile is refused by the catalog)
            raise common.UsageError(quarantines.pinned_refusal(row.episode_id))
    return _each(args, rows, lambda row: cat.quarantine(row.episode_id, args.reason),
                 lambda row: "already quarantined (the first reason stays)" if row.quarantined else "quarantined")


def _episodes_restore(args: argparse.Namespace) -> int:
    if bool(args.episode_ids) == args.all:
        raise common.UsageError("give the episodes to restore, or --all (not both)")
    cat = common.existing_catalog(args, writes=True)
    rows = cat.list(quarantined=True) if args.all else resolve_all(cat, args.episode_ids)
    if not rows and not args.json:
        print(f"nothing is quarantined in {cat.data_dir}")
    return _each(args, rows, lambda row: _restore(cat, row),
                 lambda row: "restored" if row.quarantined else "not quarantined (already in training)")


def _restore(cat: Catalog, row: EpisodeRow) -> EpisodeRow:
    """``cat.restore``, where an episode in training is left as it is (as ``quarantine`` leaves a quarantined
    one): a restore asked twice, or racing another, is not a failure."""
    try:
        return cat.restore(row.episode_id)
    except quarantines.NotQuarantinedError:
        return cat.get(row.episode_id)


def _each(args: argparse.Namespace, rows: list[EpisodeRow], change: Callable[[EpisodeRow], EpisodeRow],
          done: str | Callable[[EpisodeRow], str]) -> int:
    """Applies ``change`` to each row, reporting each (``done``: what was done, or what was done to that row as
    it was before); exit 1 when any was refused."""
    report = []
    for row in rows:
        try:
            now = change(row)
            report.append({"episode_id": row.episode_id, "ok": True, "quarantined": now.quarantined})
            if not args.json:
                said = done(row) if callable(done) else done
                print(f"{said} {row.episode_id}" + (f": {now.quarantined}" if now.quarantined else ""))
        except StorageError as exc:
            report.append({"episode_id": row.episode_id, "ok": False, "error": str(exc)})
            print(one_line(f"activecollect: {exc}"), file=sys.stderr)
    if args.json:
        common.print_json(report)
    return 0 if all(r["ok"] for r in report) else 1
