"""The eval split, and the snapshots training takes (``Catalog.pin_eval_split``, ``eval_split``, ``snapshot``).

The eval split is a fixed set of episodes indexed with split ``eval``: pinned once (tables ``eval_split``,
its hash and params, and ``eval_split_members``), it never changes for the life of the data directory, so
every model's metrics are measured on the same episodes; its hash is the content hash of their ids and
sha256s, checked whenever it is read. It fixes the catalog's one frame size (``frame_size``; before it is
pinned, the first episode does). A snapshot is the episodes of a split at one time, with a content id; a
training snapshot leaves out the eval split and quarantined episodes.

The simulator is deterministic, so an eval episode is a function of its metadata (``replay_key``): recorded
again under a new id (``activecollect collect`` with the eval split's seed), or brought in from another data
directory, it would be trained on under that id. So a train episode that replays an eval episode is refused
(``refuse_replay``, inside the transaction that would index it), and so is an eval episode that a train
episode already replays, and the pinning of one (``pin``); ``replays`` finds them, e.g. for training to leave
out what a catalog made before these checks holds.

These are the catalog's steps, over a connection it opened (``pin`` inside its ``BEGIN IMMEDIATE``
transaction); ``storage.catalog`` owns the connections and transactions.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from typing import Any

from storage import quarantine as quarantines
from storage.errors import CatalogError
from storage.records import EpisodeMeta
from storage.rows import EvalSplit, Snapshot, content_hash

#: The tables, as the catalog's schema version 1 made them (``storage.catalog._CATALOG_MIGRATIONS``): a change
#: to them is a new migration, never an edit here.
TABLES = (
    """CREATE TABLE IF NOT EXISTS eval_split (
            id INTEGER PRIMARY KEY CHECK (id = 1),
            hash TEXT NOT NULL,
            params TEXT NOT NULL,
            created TEXT NOT NULL)""",
    """CREATE TABLE IF NOT EXISTS eval_split_members (
            episode_id TEXT PRIMARY KEY REFERENCES episodes(episode_id))""",
)

#: The metadata that fixes what an episode records (``workers.collect.collect_episode``: the start state and
#: physics it is reset to, the policy, its parameters and its seed, how many prefix actions it replays, the
#: control rate): two episodes alike in these record the same frames, actions and states for as long as both
#: run. Not in it: the number of steps (a longer episode's first frames are the shorter one's, so it still
#: holds the other's windows), the frame size (a catalog holds one), and who recorded it, when, for which
#: request or model, with which software. Metadata records an action prefix by its length only (and not a
#: palette, which only recolours the objects), so episodes alike but for those count as one recording: a
#: refusal errs that way, never the other (the eval split's episodes have no prefix).
REPLAY_FIELDS: tuple[str, ...] = ("task", "shape", "physics", "start_state", "policy", "policy_params", "seed",
                                  "action_prefix_len", "control_hz")
#: Seeds compared in one query (SQLite allows 32766 parameters).
_SEEDS_PER_QUERY = 500
_INT64 = range(-2**63, 2**63)


def pin(conn: sqlite3.Connection, ids: list[str], params: dict[str, Any] | None) -> str:
    """Inside a transaction: pin the eval split to ``ids`` (sorted, at least one); return its hash.

    The same ids again return the same hash. Raises ``CatalogError`` for an unknown episode, one not of
    split ``eval``, a quarantined one, ``params`` whose ``image_size`` is not the episodes', another set
    than the one already pinned, or one that a train episode (not quarantined) replays (``replays``).
    """
    marks = ",".join("?" * len(ids))
    rows = conn.execute(f"SELECT episode_id, sha256, split FROM episodes WHERE episode_id IN ({marks})",
                        ids).fetchall()
    unknown = sorted(set(ids) - {r["episode_id"] for r in rows})
    if unknown:
        raise CatalogError(f"cannot pin unknown episodes: {', '.join(unknown[:5])}"
                           f"{' ...' if len(unknown) > 5 else ''}")
    wrong = [r["episode_id"] for r in rows if r["split"] != "eval"]
    if wrong:
        raise CatalogError(f"episodes {', '.join(wrong[:5])} are in split 'train'; only episodes "
                           "added with split='eval' can be pinned")
    held = quarantines.quarantined_among(conn, ids)
    if held:
        raise CatalogError(f"episodes {', '.join(held[:5])} are quarantined; restore them first, or pin "
                           "others")
    sizes = {r[0] for r in conn.execute(f"SELECT DISTINCT json_extract(meta, '$.image_size') FROM episodes "
                                        f"WHERE episode_id IN ({marks})", ids)}
    said = (params or {}).get("image_size")
    if said is not None and ({said} != sizes or isinstance(said, bool)):
        raise CatalogError(f"params say image_size {said!r}, the episodes have "
                           f"{', '.join(map(str, sorted(sizes)))}px frames")
    digest = content_hash([(r["episode_id"], r["sha256"]) for r in rows])
    current = conn.execute("SELECT hash FROM eval_split WHERE id = 1").fetchone()
    if current is not None:
        if current["hash"] != digest:
            raise CatalogError(f"an eval split is already pinned (hash {current['hash'][:16]}); "
                               "it cannot be replaced")
        return digest
    pinning = set(ids)
    copies = sorted((e, t) for e, t in replays(conn, "eval").items() if e in pinning)
    if copies:
        (first, train), more = copies[0], len(copies) - 1
        raise CatalogError(f"eval episode {first} is replayed by train episode {train}"
                           f"{f' (and {more} more eval episodes by train episodes)' if more else ''}: models "
                           f"trained on it would be measured on their own training data; quarantine {train} "
                           "(`activecollect episodes quarantine`) or pin other episodes")
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    conn.execute("INSERT INTO eval_split(id, hash, params, created) VALUES (1, ?, ?, ?)",
                 (digest, json.dumps(params or {}, sort_keys=True), created))
    conn.executemany("INSERT INTO eval_split_members(episode_id) VALUES (?)", [(i,) for i in ids])
    return digest


def read(conn: sqlite3.Connection) -> EvalSplit | None:
    """The pinned eval split, or None. ``CatalogError`` if its rows no longer match its hash."""
    head = conn.execute("SELECT hash, params, created FROM eval_split WHERE id = 1").fetchone()
    if head is None:
        return None
    rows = conn.execute("SELECT m.episode_id, e.sha256 FROM eval_split_members m "
                        "JOIN episodes e USING (episode_id) ORDER BY m.episode_id").fetchall()
    digest = content_hash([(r["episode_id"], r["sha256"]) for r in rows])
    if digest != head["hash"]:
        raise CatalogError(f"the pinned eval split's episodes hash to {digest[:16]}, "
                           f"pinned as {head['hash'][:16]}")
    return EvalSplit(ids=[r["episode_id"] for r in rows], hash=head["hash"],
                     params=json.loads(head["params"]), created=head["created"])


def frame_size(conn: sqlite3.Connection) -> tuple[int, str] | None:
    """(frame size, what fixed it) of a catalog: its pinned eval split's, else its first episode's; None
    while it holds no episode."""
    row = conn.execute("SELECT json_extract(params, '$.image_size'), json_type(params, '$.image_size') "
                       "FROM eval_split WHERE id = 1").fetchone()
    if row is not None and row[1] == "integer":
        return row[0], "its eval split"
    first = conn.execute("SELECT episode_id, json_extract(meta, '$.image_size') FROM episodes "
                         "ORDER BY rowid LIMIT 1").fetchone()
    if first is not None and isinstance(first[1], int):
        return first[1], f"its first episode, {first[0]}"
    return None


def snapshot(conn: sqlite3.Connection, split: str) -> Snapshot:
    """The episodes of ``split`` now, less the quarantined ones and, for ``train``, the eval split's."""
    rows = conn.execute(
        f"SELECT episode_id, sha256 FROM episodes WHERE split = ? AND {quarantines.NOT_QUARANTINED}"
        + (" AND episode_id NOT IN (SELECT episode_id FROM eval_split_members)" if split == "train" else "")
        + " ORDER BY episode_id", (split,)).fetchall()
    return Snapshot.of([(r["episode_id"], r["sha256"]) for r in rows])


def replay_key(meta: EpisodeMeta | Mapping[str, Any]) -> str:
    """What makes two episodes one recording (``REPLAY_FIELDS`` of an ``EpisodeMeta`` or of its JSON form), as
    a string: equal for two episodes that replay each other. A number counts by its value (1 and 1.0 alike)."""
    raw = json.loads(meta.to_json()) if isinstance(meta, EpisodeMeta) else meta
    return json.dumps([_by_value(raw.get(name)) for name in REPLAY_FIELDS], sort_keys=True)


def _by_value(value: Any) -> Any:
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, dict):
        return {str(k): _by_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_by_value(v) for v in value]
    return value


def replays(conn: sqlite3.Connection, split: str,
            metas: Sequence[EpisodeMeta] | None = None, *, within: bool = False) -> dict[str, str]:
    """The episodes of ``split`` that replay an episode of the other split (same ``replay_key``): {their id:
    the other's id (the first by id)}. ``metas``: episodes about to be indexed in ``split``, instead of the
    indexed ones. ``within`` (with ``metas`` only): those that replay an episode of ``split`` itself (the same
    episode collected twice).

    Every eval episode counts, pinned or not (an unpinned one waits to be pinned: ``eval-split pin`` takes
    them all), quarantined or not; quarantined train episodes do not (nothing trains on them: quarantining
    the copy is how an operator lets its eval episode be pinned).
    """
    if within and metas is None:
        raise ValueError("replays(within=True) compares the episodes about to be indexed: give metas")
    other = split if within else "eval" if split == "train" else "train"
    if metas is not None:
        mine = [(m.episode_id, json.loads(m.to_json())) for m in metas]
        theirs = _rows(conn, other, [raw.get("seed") for _, raw in mine])
    elif split == "eval":
        mine = _rows(conn, "eval")
        theirs = _rows(conn, "train", [raw.get("seed") for _, raw in mine])
    else:
        theirs = _rows(conn, "eval")
        mine = _rows(conn, "train", [raw.get("seed") for _, raw in theirs])
    first: dict[str, str] = {}
    for episode_id, raw in sorted(theirs, key=lambda r: r[0]):
        first.setdefault(replay_key(raw), episode_id)
    return {episode_id: first[key] for episode_id, raw in mine if (key := replay_key(raw)) in first}


def _rows(conn: sqlite3.Connection, split: str, seeds: list[Any] | None = None) -> list[tuple[str, dict]]:
    """(id, metadata) of the episodes of ``split`` (train: those not quarantined), of one of ``seeds`` when
    given: a replay has its episode's seed, so only those are parsed. A seed SQLite cannot hold as a parameter
    (not an int64) reads them all."""
    sql = "SELECT episode_id, meta FROM episodes WHERE split = ?" + (
        f" AND {quarantines.NOT_QUARANTINED}" if split == "train" else "")
    if seeds is not None and not all(isinstance(s, int) and not isinstance(s, bool) and s in _INT64 for s in seeds):
        seeds = None
    if seeds is None:
        found = conn.execute(sql, (split,)).fetchall()
    else:
        wanted, found = sorted(set(seeds)), []
        for i in range(0, len(wanted), _SEEDS_PER_QUERY):
            chunk = wanted[i:i + _SEEDS_PER_QUERY]
            found += conn.execute(f"{sql} AND json_extract(meta, '$.seed') IN ({','.join('?' * len(chunk))})",
                                  (split, *chunk)).fetchall()
    return [(r["episode_id"], json.loads(r["meta"])) for r in found]


def refuse_replay(conn: sqlite3.Connection, meta: EpisodeMeta, split: str) -> None:
    """Inside the transaction that indexes ``meta`` in ``split``: ``CatalogError`` naming the episode of the
    other split it replays (``replays``), if any."""
    other = replays(conn, split, [meta]).get(meta.episode_id)
    if other is None:
        return
    if split == "train":
        raise CatalogError(f"episode {meta.episode_id} replays eval episode {other} (the same start state, "
                           "physics, policy and seed): training on it would leak the eval split")
    raise CatalogError(f"episode {meta.episode_id} replays train episode {other} (the same start state, "
                       "physics, policy and seed): models trained on that one would be measured on their own "
                       "training data")
