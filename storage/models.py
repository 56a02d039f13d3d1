"""The model registry: versioned checkpoints on disk, their rows in the catalog, and the promotion gate.

Layout: ``DATA/models/<version>/`` holds ``weights.pt`` (opaque bytes, whatever the trainer
serialised), ``config.json``, ``metrics.json`` (strict JSON: NaN as null, where the row keeps NaN), ``meta.json``
(snapshot id, eval split hash, parent, created, sha256 of the weights) and ``snapshot.json`` (the training
episodes' ids and sha256s, when the trainer gave them; they hash to the snapshot id). The rows live in the
``models`` table of ``DATA/catalog.sqlite`` next to the episodes; the alias ``champion`` (table ``model_aliases``)
names the model in service and ``champion_history`` remembers every promotion, so a rollback can walk back.

Versions are ``m<6-digit sequence>-<8 hex of the weights' sha256>``: unique, and they sort in
registration order. Every change is one ``BEGIN IMMEDIATE`` transaction, so the alias switch is atomic.
The tables are created through ``storage.database.ensure_schema`` (component ``models``).

Retention: nothing is deleted unless asked. ``prune(keep=N)`` deletes the files of retired and
rejected models outside the champion's rollback chain of N; their rows stay (``pruned_at`` set), so
``models ls`` and the dashboard still show every model's metrics and history. Folders no row names (a
register killed before its commit) go aside to ``DATA/models/.orphans/`` (``sweep_strays``, ``prune``); the
dot folders of registers and prunes killed midway are deleted once stale (both too).

The rows the registry answers with are ``storage.model_rows``'s dataclasses (re-exported here), the steps
of a prune ``storage.pruning``'s functions, the champion alias, its history and every status change
``storage.promotions``'s, the gate's verdict ``storage.gate``'s; a checkpoint directory's files are written, read
back and checked by ``storage.checkpoint_files`` (with the verdicts ``weights_problem`` remembers).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import sqlite3
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import Any

from storage import checkpoint_files, errors, jsonsafe, promotions, pruning, strays
from storage.database import (DB_NAME, MODELS_DIR, Migration, connection, ensure_schema, refuse_lost_database,
                              storage_error, transaction, undo_unless_committed)
from storage.errors import CorruptCheckpointError, RegistryError, RegistryUnavailableError, UnknownModelError
from storage.files import make_folder, write_synced
from storage.gate import DEFAULT_METRIC, DEFAULT_MIN_REL_IMPROVEMENT, GateDecision, diverged, judge
from storage.model_rows import (CONFIG_FILE, META_FILE, METRICS_FILE, SNAPSHOT_FILE, WEIGHTS_FILE, ChampionEntry,
                                ModelRecord, ModelStatus, PruneResult, StrayFolders, record_of)
from storage.promotions import CHAMPION, now
from storage.rows import Snapshot

__all__ = ["CHAMPION", "MODELS_DIR", "WEIGHTS_FILE", "ChampionEntry", "GateDecision", "ModelRecord", "ModelRegistry",
           "ModelStatus", "PruneResult", "StrayFolders"]

#: One entry per schema version; a change to the tables is a new entry at the end. Each says which older
#: code may still use the file after it (``compatible_with``, see ``storage.database.Migration``): leave
#: the default, its own version, unless that code can neither misread nor damage the new shape.
_MIGRATIONS: tuple[Migration, ...] = (
    Migration((
        """CREATE TABLE IF NOT EXISTS models (
            version TEXT PRIMARY KEY,
            seq INTEGER NOT NULL UNIQUE,
            status TEXT NOT NULL,
            reason TEXT NOT NULL DEFAULT '',
            parent TEXT,
            snapshot_id TEXT NOT NULL,
            eval_split_hash TEXT NOT NULL,
            weights_sha256 TEXT NOT NULL,
            size_bytes INTEGER NOT NULL,
            created TEXT NOT NULL,
            updated TEXT NOT NULL,
            metrics TEXT NOT NULL,
            config TEXT NOT NULL)""",
        "CREATE INDEX IF NOT EXISTS models_status ON models(status)",
        """CREATE TABLE IF NOT EXISTS model_aliases (
            alias TEXT PRIMARY KEY,
            version TEXT NOT NULL REFERENCES models(version))""",
        """CREATE TABLE IF NOT EXISTS champion_history (
            id INTEGER PRIMARY KEY AUTOINCREMENT,
            version TEXT NOT NULL REFERENCES models(version),
            promoted_at TEXT NOT NULL,
            reason TEXT NOT NULL,
            rolled_back_at TEXT)""",
    )),
    # Not for version-1 code, which would take a pruned model (its files deleted) for one it can load: a
    # rollback target, weights to serve.
    Migration(("ALTER TABLE models ADD COLUMN pruned_at TEXT",), compatible_with=2),
)


def _dump(obj: Any, what: str, finite: bool = False) -> bytes:
    try:  # (finite: NaN and infinities as null, for a file strict readers take; a row keeps them, the gate reads it)
        return json.dumps(jsonsafe.finite_json(obj) if finite else obj, sort_keys=True, indent=2).encode()
    except (TypeError, ValueError) as exc:
        raise RegistryError(f"{what} must be JSON-serialisable: {exc}") from exc


class ModelRegistry:
    """Checkpoints under ``data_dir/models`` and their rows in ``data_dir/catalog.sqlite``.

    Safe to use from several threads and processes: each call opens its own connection and every
    change is one ``BEGIN IMMEDIATE`` transaction.
    """

    def __init__(self, data_dir: str | os.PathLike[str], make_models_dir: bool = True) -> None:
        self.data_dir = Path(data_dir)
        refuse_lost_database(self.data_dir, RegistryError)
        self.models_dir = self.data_dir / MODELS_DIR
        make_folder(self.models_dir, errors.RegistryFolderError, "the registry keeps its checkpoints there",
                    create=make_models_dir)  # (False: a reader that must write nothing; it stores no checkpoint)
        self.db_path = self.data_dir / DB_NAME
        with self._connect() as conn:
            ensure_schema(conn, "models", _MIGRATIONS, RegistryError)

    # -- connections ---------------------------------------------------------------------------

    def _connect(self) -> AbstractContextManager[sqlite3.Connection]:
        return connection(self.db_path, RegistryError)  # the catalog's settings: WAL, busy timeout, FULL sync

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._connect() as conn, transaction(conn):
            yield conn

    # -- reading -------------------------------------------------------------------------------

    def _record(self, row: sqlite3.Row) -> ModelRecord:
        return record_of(row, self.models_dir)

    def _get(self, conn: sqlite3.Connection, version: str) -> ModelRecord:
        row = conn.execute("SELECT * FROM models WHERE version = ?", (version,)).fetchone()
        if row is None:
            known = [r[0] for r in conn.execute("SELECT version FROM models ORDER BY seq DESC LIMIT 5")]
            hint = f"; latest: {', '.join(known)}" if known else "; the registry is empty"
            raise UnknownModelError(f"unknown model version {version!r}{hint}")
        return self._record(row)

    @staticmethod
    def _registered(conn: sqlite3.Connection, version: str) -> bool:
        return conn.execute("SELECT 1 FROM models WHERE version = ?", (version,)).fetchone() is not None

    def get(self, version: str) -> ModelRecord:
        """The record of ``version``; raises ``RegistryError`` if it is not registered."""
        with self._connect() as conn:
            return self._get(conn, version)

    def resolve(self, version_or_prefix: str) -> ModelRecord:
        """The model whose version is ``version_or_prefix`` or uniquely starts with it (for the CLI).

        Raises ``UnknownModelError`` when none does, or more than one (naming them).
        """
        with self._connect() as conn:
            row = conn.execute("SELECT * FROM models WHERE version = ?", (version_or_prefix,)).fetchone()
            if row is None and version_or_prefix:
                rows = conn.execute("SELECT * FROM models WHERE substr(version, 1, ?) = ? ORDER BY seq LIMIT 4",
                                    (len(version_or_prefix), version_or_prefix)).fetchall()
                if len(rows) > 1:
                    shown = ", ".join(r["version"] for r in rows[:3]) + (", ..." if len(rows) > 3 else "")
                    raise UnknownModelError(f"model version prefix {version_or_prefix!r} is ambiguous ({shown})")
                row = rows[0] if rows else None
            return self._get(conn, version_or_prefix) if row is None else self._record(row)  # _get: the error

    def list(self, status: ModelStatus | str | None = None) -> list[ModelRecord]:
        """All models in registration order, optionally only those with ``status``."""
        if status is not None and status not in {s.value for s in ModelStatus}:
            raise RegistryError(f"status must be one of {', '.join(s.value for s in ModelStatus)}, "
                                f"found {status!r}")
        with self._connect() as conn:
            if status is None:
                rows = conn.execute("SELECT * FROM models ORDER BY seq").fetchall()
            else:
                rows = conn.execute("SELECT * FROM models WHERE status = ? ORDER BY seq",
                                    (ModelStatus(status).value,)).fetchall()
        return [self._record(r) for r in rows]

    def newest(self) -> ModelRecord | None:
        """The model registered last, or None when there is none (one row read, whatever the history)."""
        with self._connect() as conn:
            row = conn.execute("SELECT * FROM models ORDER BY seq DESC LIMIT 1").fetchone()
        return None if row is None else self._record(row)

    def champion(self) -> str | None:
        """The version in service, or None before the first promotion."""
        with self._connect() as conn:
            return promotions.champion(conn)

    def history(self) -> list[ChampionEntry]:
        """Every promotion, oldest first (rolled-back ones carry ``rolled_back_at``)."""
        with self._connect() as conn:
            return promotions.history(conn)

    def load_weights(self, version: str) -> bytes:
        """The weights bytes of ``version``, checked against their recorded sha256.

        Raises ``RegistryError`` for an unknown version and ``CorruptCheckpointError`` when the
        file is missing, unreadable or does not match its sha256.
        """
        return self._read_verified(self.get(version))

    def verify(self, version: str) -> None:
        """Raise ``CorruptCheckpointError`` unless the weights of ``version`` match their sha256."""
        self.load_weights(version)

    def check_ready(self, champion: bool = True) -> None:
        """Raise ``RegistryUnavailableError`` when a job's register or gate would fail now for a reason that may
        pass: ``models/`` cannot take a checkpoint (read-only, full), or (``champion``) the champion's weights,
        which the gate compares against, cannot be read. For a training job to ask before it trains, not after
        (one that warm-starts reads the champion's weights first anyway, and says so in its own words)."""
        try:
            shutil.rmtree(checkpoint_files.stage(self.models_dir, {"probe": b""}))
        except OSError as exc:
            raise RegistryUnavailableError(f"cannot store a checkpoint in {self.models_dir} now: "
                                           f"{exc.strerror or exc} (nothing trained)") from exc
        current = self.champion() if champion else None
        if current is not None:
            try:
                self.verify(current)
            except CorruptCheckpointError as exc:  # a damaged one (for good): the gate replaces it
                checkpoint_files.raise_unless_lasting(exc, f"read champion {current}, which the gate compares "
                                                      "against")

    def snapshot(self, version: str) -> Snapshot | None:
        """The episodes ``version`` was trained on (ids and sha256s, sorted by id), or None when it was
        registered without them (by a trainer older than ``snapshot.json``).

        Raises ``RegistryError`` for an unknown version, ``PrunedCheckpointError`` when its files were
        pruned, and ``CorruptCheckpointError`` when the file cannot be read or does not hash to the
        model's snapshot id.
        """
        return checkpoint_files.read_snapshot(self.get(version))

    def weights_problem(self, version: str) -> str | None:
        """Why the weights of ``version`` cannot be served (pruned, missing, unreadable, not their sha256),
        or None when they can. A verdict on the bytes is remembered per state of the weights file
        (``file_state``) for ``WEIGHTS_RECHECK_S`` (both ``storage.checkpoint_files``'s), so what asks again
        and again (the dashboard, ``stats``) re-reads the file only when it has changed or that long has
        passed; a read that failed (which may pass) is not remembered."""
        return checkpoint_files.weights_problem(self.get(version), self._read_verified)

    def _read_verified(self, rec: ModelRecord) -> bytes:
        """Every read of a model's weights goes through here (``checkpoint_files.read_weights``)."""
        return checkpoint_files.read_weights(rec)

    # -- registering ---------------------------------------------------------------------------

    def register(self, weights: bytes, config: dict[str, Any], metrics: dict[str, Any], snapshot_id: str,
                 eval_split_hash: str, parent: str | None = None, snapshot: Snapshot | None = None) -> str:
        """Store a new checkpoint as a ``candidate`` and return its version.

        ``snapshot``: the episodes it was trained on (``snapshot.json``, read back by ``snapshot``); its id
        must be ``snapshot_id``. The directory is written under a temporary name, fsynced and renamed
        before the row is committed, so a registered version always has complete files. Raises
        ``RegistryError`` for empty weights, non-JSON config/metrics, empty ids, a ``snapshot`` of another
        id or an unknown ``parent``.
        """
        if not isinstance(weights, (bytes, bytearray, memoryview)) or len(weights) == 0:
            raise RegistryError(f"weights must be non-empty bytes, found {type(weights).__name__} "
                                f"of length {len(weights) if hasattr(weights, '__len__') else '?'}")
        for name, value in (("snapshot_id", snapshot_id), ("eval_split_hash", eval_split_hash)):
            if not isinstance(value, str) or not value:
                raise RegistryError(f"{name} must be a non-empty string, found {value!r}")
        if not isinstance(config, dict) or not isinstance(metrics, dict):
            raise RegistryError(f"config and metrics must be dicts, found {type(config).__name__} "
                                f"and {type(metrics).__name__}")
        files = {}
        if snapshot is not None:
            files[SNAPSHOT_FILE] = checkpoint_files.snapshot_json(snapshot, snapshot_id)
        weights = bytes(weights)
        sha = hashlib.sha256(weights).hexdigest()
        config_bytes, metrics_bytes = _dump(config, "config"), _dump(metrics, "metrics")
        created = now()
        # The big writes and their fsyncs happen before taking the write lock (leases wait on it).
        tmp = None
        try:
            tmp = checkpoint_files.stage(self.models_dir, {WEIGHTS_FILE: weights, CONFIG_FILE: config_bytes, **files,
                                                           METRICS_FILE: _dump(metrics, "metrics", finite=True)})
            with self._connect() as conn:
                try:
                    with transaction(conn):
                        if parent is not None:
                            self._get(conn, parent)
                        seq = conn.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM models").fetchone()[0]
                        version = f"m{seq:06d}-{sha[:8]}"
                        meta = {"version": version, "snapshot_id": snapshot_id, "eval_split_hash": eval_split_hash,
                                "parent": parent, "created": created, "weights_sha256": sha,
                                "size_bytes": len(weights), "weights_file": WEIGHTS_FILE}
                        write_synced(tmp / META_FILE, _dump(meta, "meta"))
                        checkpoint_files.publish(self.models_dir, tmp, version)
                        conn.execute(
                            "INSERT INTO models (version, seq, status, reason, parent, snapshot_id, "
                            "eval_split_hash, weights_sha256, size_bytes, created, updated, metrics, config) "
                            "VALUES (?, ?, ?, '', ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                            (version, seq, ModelStatus.CANDIDATE.value, parent, snapshot_id, eval_split_hash,
                             sha, len(weights), created, created, metrics_bytes.decode(), config_bytes.decode()))
                except BaseException as exc:
                    if not tmp.exists():  # published (maybe not returned: a signal's exception in its fsync):
                        final = self.models_dir / version  # removed under the write lock unless its row committed
                        undo_unless_committed(conn, lambda c: self._registered(c, version),
                                              lambda: shutil.rmtree(final, ignore_errors=True), exc, str(final))
                    raise
        except OSError as exc:  # a full disk: nothing registered
            raise storage_error(exc, RegistryError, f"cannot store a checkpoint in {self.models_dir}: "
                                f"{exc.strerror or exc}", self.models_dir) from exc
        finally:
            if tmp is not None and tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        return version

    # -- the gate and the alias ----------------------------------------------------------------

    def gate(self, version: str, min_rel_improvement: float = DEFAULT_MIN_REL_IMPROVEMENT,
             metric: str = DEFAULT_METRIC, eval_split_hash: str | None = None) -> GateDecision:
        """Promote ``version`` to champion only if it is measurably better; otherwise mark it rejected.

        Checks, in order: the weights match their sha256; the candidate was evaluated on the current
        eval split (``eval_split_hash`` if given, else the champion's); the gate metric and every
        ``h1_*`` metric are finite; and ``metric`` < champion's ``metric * (1 - min_rel_improvement)``.
        The first model needs only the first three. A refused candidate is kept with status
        ``rejected`` and the reason; a version that is no longer a candidate (rejected, retired) is
        refused without any change. Raises ``RegistryError`` for an unknown version or a bad
        ``min_rel_improvement``, ``RegistryUnavailableError`` when a weights file cannot be read now.
        """
        if not 0 <= min_rel_improvement < 1:
            raise RegistryError(f"min_rel_improvement must be in [0, 1), found {min_rel_improvement}")
        rec = self.get(version)
        if rec.status not in (ModelStatus.CANDIDATE, ModelStatus.CHAMPION):
            return self._not_a_candidate(rec, self.champion(), metric)
        try:
            self._read_verified(rec)
        except CorruptCheckpointError as exc:
            checkpoint_files.raise_unless_lasting(exc, f"gate {version}")  # it stays a candidate
            return self._refuse(rec, f"corrupt checkpoint: {exc}", metric)
        # A champion whose weights fail their sha256 serves nothing: any sound candidate replaces it
        # (checked before the write lock: it reads files).
        checked, unusable = self.champion(), ""
        if checked is not None and checked != version:
            try:
                self.verify(checked)
            except CorruptCheckpointError as exc:
                checkpoint_files.raise_unless_lasting(exc, f"gate {version} against champion {checked}")
                unusable = str(exc)
        with self._transaction() as conn:
            current = promotions.champion(conn)
            if current == version:  # promoted by an operator between its register and its gate: it *is* champion
                before, how = promotions.how_promoted(conn, version)
                return GateDecision(True, f"{version} is already the champion ({how})", version, before, metric)
            now = self._get(conn, version)
            if now.status != ModelStatus.CANDIDATE:  # a rolled-back or refused model is not re-judged
                return self._not_a_candidate(now, current, metric)
            champ = self._get(conn, current) if current is not None else None
            promoted, reason, champ_value = judge(rec, champ, metric, min_rel_improvement, eval_split_hash,
                                                  unusable if current == checked else "")
            if promoted:
                promotions.switch(conn, version, reason)
            else:
                promotions.set_status(conn, version, ModelStatus.REJECTED, reason)
        cand_value = rec.metrics.get(metric)
        return GateDecision(promoted, reason, version, current, metric,
                            cand_value if isinstance(cand_value, (int, float)) else None, champ_value)

    @staticmethod
    def _not_a_candidate(rec: ModelRecord, current: str | None, metric: str) -> GateDecision:
        return GateDecision(False, f"{rec.version} is {rec.status.value}, not a candidate: only a new candidate "
                            "goes through the gate (models promote overrides it)", rec.version, current, metric)

    def _refuse(self, rec: ModelRecord, reason: str, metric: str) -> GateDecision:
        with self._transaction() as conn:
            current = promotions.champion(conn)
            if current != rec.version:
                promotions.set_status(conn, rec.version, ModelStatus.REJECTED, reason)
        value = rec.metrics.get(metric)
        return GateDecision(False, reason, rec.version, current, metric,
                            value if isinstance(value, (int, float)) else None)

    def promote(self, version: str, eval_split_hash: str | None = None,
                reason: str = "promoted by the operator") -> GateDecision:
        """Make ``version`` the champion without comparing metrics (the operator's override). Still refuses, by
        raising, a checkpoint whose weights do not match their sha256 (``CorruptCheckpointError``), one whose
        training diverged (``gate.diverged``) and one evaluated on another eval split than ``eval_split_hash`` (or
        the champion's when not given) (``RegistryError``)."""
        rec = self.get(version)
        if (bad := diverged(rec.metrics)) is not None:
            raise RegistryError(f"refusing to promote {version}: {bad}: its training diverged, it predicts no numbers")
        self._read_verified(rec)
        with self._transaction() as conn:
            current = promotions.champion(conn)
            if current == version:
                return GateDecision(False, f"{version} is already the champion", version, current)
            checkpoint_files.refuse_pruned(self._get(conn, version))  # a prune may have landed since the sha256 check
            champ = self._get(conn, current) if current is not None else None
            expected = eval_split_hash if eval_split_hash is not None else (champ.eval_split_hash if champ else None)
            if expected is not None and rec.eval_split_hash != expected:
                raise RegistryError(
                    f"refusing to promote {version}: it was evaluated on eval split "
                    f"{rec.eval_split_hash}, the current eval split is {expected}")
            promotions.switch(conn, version, reason)
        return GateDecision(True, reason, version, current)

    def rollback(self, eval_split_hash: str | None = None) -> str:
        """Return to the previous champion whose weights still match their sha256; return its version.

        Previous champions with corrupt or missing weights are skipped, and so are those evaluated on another
        eval split than ``eval_split_hash`` (or the champion's when not given), which ``promote`` refuses. The
        rolled-back champion becomes ``retired``. Raises ``RegistryError`` when there is no champion or no
        earlier one to return to, ``RegistryUnavailableError`` when one's weights cannot be read now (nothing
        changes).
        """
        with self._connect() as conn:
            current, entries = promotions.champion(conn), promotions.live_history(conn)
            if current is None:
                raise RegistryError("no champion to roll back from: nothing has been promoted yet")
            split = eval_split_hash if eval_split_hash is not None else self._get(conn, current).eval_split_hash
            other = dict(conn.execute("SELECT version, eval_split_hash FROM models WHERE eval_split_hash != ?",
                                      (split,)).fetchall())
        # Checking sha256 reads files; do it before taking the write lock, then re-check the state.
        target = promotions.rollback_target(entries, current, self.verify, other)
        with self._transaction() as conn:
            promotions.roll_back(conn, current, target, entries)
        return target

    def reject_candidates(self, reason: str) -> list[str]:
        """Mark every ``candidate`` rejected with ``reason``, in one transaction; return their versions.

        For the one job that may register and gate (the retrain lock's holder): at its start a
        candidate can only be one an earlier job registered and never gated (killed, or its gate's
        transaction failed). Rejected, it is kept with the reason and ``prune`` may delete its files;
        ``promote`` still takes it.
        """
        with self._transaction() as conn:
            left = [r[0] for r in conn.execute("SELECT version FROM models WHERE status = ? ORDER BY seq",
                                               (ModelStatus.CANDIDATE.value,))]
            for version in left:
                promotions.set_status(conn, version, ModelStatus.REJECTED, reason)
        return left

    # -- retention -----------------------------------------------------------------------------

    def prune(self, keep: int, dry_run: bool = False) -> PruneResult:
        """Delete the files of retired and rejected models, except the ``keep`` newest of the rollback chain.

        Kept always: the champion (``keep`` counts it), the ``keep - 1`` earlier champions that
        ``rollback`` walks back to (one whose weights fail their sha256 or are missing does not count:
        rollback would skip it), and every candidate (a retrain job may be about to gate it). One whose
        weights cannot be read now (an I/O error, which may pass) is kept too, and does not count either.
        Slots the chain leaves go to the latest champions a rollback took out of service (so they can be
        promoted again). Pruned rows stay, with ``pruned_at`` set: their metrics and history remain, their
        weights are refused with ``PrunedCheckpointError`` and ``rollback`` skips them. The rows are marked in one
        transaction before any file is deleted, so a crash between leaves marked rows whose files the next
        ``prune`` deletes; one whose directory cannot be deleted (``PruneResult.not_deleted``) and is still
        whole gets its mark taken off again, usable as before; each directory is claimed by a rename before
        it is deleted, so two prunes at once delete (and count) it once. Also sweeps the dot folders crashed calls
        left, and moves the folders no row names aside (``sweep_strays``; ``orphaned``, and ``not_moved``
        those that could not be, which fail nothing). Raises ``RegistryError`` for a ``keep`` below 1.
        """
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
            raise RegistryError(f"keep must be a whole number of at least 1 (the champion), found {keep!r}")
        # Which of the chain rollback could return to: checking sha256 reads files, so before the lock
        # (a model promoted meanwhile is not in `unusable` and is kept).
        with self._connect() as conn:
            wanted = self._keep_order(conn)
        unusable, unread = pruning.check(wanted, keep, self.verify)
        folders = strays.model_folders(self.models_dir)
        with self._transaction() as conn:
            kept = pruning.kept(self._keep_order(conn), keep, unusable, unread)
            chosen = pruning.mark(conn, kept, None if dry_run else now())
            marked = pruning.marked(conn)
            aside = strays.unregistered(conn, folders, self._orphans(dry_run))  # a failed move fails nothing
        if dry_run:
            return pruning.dry_run(self.models_dir, chosen, marked, kept, aside)
        with self._transaction() as conn:  # the marks committed first: a crash then leaves marks the next deletes
            claimed, failed = pruning.claim(conn, self.models_dir, chosen + [v for v in marked if v not in chosen],
                                            now(), lambda version: self._whole(conn, version))
        return pruning.finish(self.models_dir, chosen, claimed, failed, kept, aside)

    def _whole(self, conn: sqlite3.Connection, version: str) -> bool:
        """Whether the weights of ``version`` (marked pruned, its folder there) are at their registered size: by
        ``stat``, under the write lock (rollback and promote check the sha256 before they use them)."""
        rec = self._get(conn, version)
        try:
            return rec.weights_path.stat().st_size == rec.size_bytes
        except FileNotFoundError:
            return False
        except OSError:
            return True

    def sweep_strays(self, dry_run: bool = False) -> StrayFolders:
        """Move the checkpoint folders no row names (a register killed before its commit: nothing acknowledged)
        to ``DATA/models/.orphans/``; say which moved and which could not (``dry_run``: only find them). Checked
        under the write lock, so never a live register's, in any process (``storage.strays.unregistered``).
        Also deletes the dot folders killed registers and prunes left, as ``prune`` does (``StrayFolders.stale``)."""
        folders = strays.model_folders(self.models_dir)  # listed before the write lock, checked under it
        with self._transaction() as conn:
            found = strays.unregistered(conn, folders, self._orphans(dry_run))
        return dataclasses.replace(found, stale=pruning.sweep_stale(self.models_dir, time.time(), dry_run))

    def _orphans(self, dry_run: bool) -> Path | None:
        return None if dry_run else self.data_dir / strays.MODEL_ORPHANS_DIR

    def _keep_order(self, conn: sqlite3.Connection) -> list[str]:
        """What ``prune`` keeps first (``storage.pruning.keep_order``)."""
        return pruning.keep_order(conn, promotions.champion(conn), promotions.live_history(conn))
