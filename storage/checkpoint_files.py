"""A checkpoint directory's files, ``DATA/models/<version>/`` (their names are ``storage.model_rows``'s).

Writing (``ModelRegistry.register``): ``stage`` writes the files into a fresh ``.tmp-*`` directory, each
fsynced, before the registry takes its write lock; ``publish``, under it, renames the directory to its
version. ``snapshot_json`` is what ``snapshot.json`` holds. Reading: ``read_weights`` checks the weights
against their recorded sha256 and ``read_snapshot`` the training episodes against the snapshot id; both refuse
a pruned model (``refuse_pruned``). ``weights_problem`` says why the weights cannot be served and remembers
its verdicts, per state of the file (``file_state``), for ``WEIGHTS_RECHECK_S``.

They take a model's row (``storage.model_rows.ModelRecord``); the rows, connections and transactions are
``storage.models``'s.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from storage.errors import CorruptCheckpointError, PrunedCheckpointError, RegistryError, RegistryUnavailableError
from storage.files import fsync_dir, write_synced
from storage.model_rows import SNAPSHOT_FILE, ModelRecord
from storage.rows import Snapshot

#: ``weights_problem``'s verdicts on what a file holds, by the state of the file it read: ``(path, sha256,
#: pruned_at, *file_state)`` -> (the problem or None, when). Process-wide, as what polls it (the dashboard's
#: handler threads) opens a registry per thread. A verdict is kept ``WEIGHTS_RECHECK_S`` at most, so media
#: damage that leaves the file's times alone is found too.
_CHECKED: dict[tuple, tuple[str | None, float]] = {}
_CHECKED_LOCK = threading.Lock()
_CHECKED_MAX = 256
WEIGHTS_RECHECK_S = 300.0


def file_state(path: Path) -> tuple[int, int, int, int] | None:
    """``(size, mtime_ns, ctime_ns, inode)`` of ``path``, None when it cannot be read: what changes when the
    file, or who may read it, does."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino


# -- writing -----------------------------------------------------------------------------------


def snapshot_json(snapshot: Snapshot, snapshot_id: str) -> bytes:
    """What ``snapshot.json`` holds for the episodes ``snapshot``; ``RegistryError`` unless they are
    ``snapshot_id`` (sorted by id, one sha256 each)."""
    pairs = list(zip(snapshot.ids, snapshot.sha256s))
    if not snapshot.is_of(snapshot_id):
        raise RegistryError(f"the {len(snapshot.ids)} episodes given are not snapshot {snapshot_id!r} "
                            f"(sorted by id, one sha256 each); they hash to {Snapshot.of(pairs).snapshot_id!r}")
    return json.dumps({"snapshot_id": snapshot_id, "episodes": pairs}, separators=(",", ":")).encode()


def stage(models_dir: Path, files: dict[str, bytes]) -> Path:
    """Write ``files`` into a fresh temporary directory under ``models_dir``, each fsynced."""
    tmp = models_dir / f".tmp-{uuid.uuid4().hex}"
    tmp.mkdir()
    try:
        for name, data in files.items():
            write_synced(tmp / name, data)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp


def publish(models_dir: Path, tmp: Path, version: str) -> Path:
    """Under the write lock: rename the staged ``tmp`` to ``models_dir/<version>`` durably."""
    final = models_dir / version
    if final.exists():
        # No row names this version (we hold the write lock and seq is new): a crash left it
        # between rename and commit. Nothing references it, so it can go.
        shutil.rmtree(final)
    fsync_dir(tmp)
    os.rename(tmp, final)
    fsync_dir(models_dir)
    return final


# -- reading -----------------------------------------------------------------------------------


def refuse_pruned(rec: ModelRecord) -> None:
    """``PrunedCheckpointError`` when the files of ``rec`` were pruned."""
    if rec.pruned_at is not None:
        raise PrunedCheckpointError(f"checkpoint {rec.version}: weights pruned at {rec.pruned_at} "
                                    "(models prune); its metrics and history remain")


def read_weights(rec: ModelRecord) -> bytes:
    """The weights bytes of ``rec``, checked against their recorded sha256.

    Raises ``PrunedCheckpointError`` when they were pruned and ``CorruptCheckpointError`` when the file is
    missing, unreadable or does not match its sha256 (``lasting`` tells a read that failed from the rest).
    """
    refuse_pruned(rec)
    try:
        data = rec.weights_path.read_bytes()
    except FileNotFoundError:
        raise CorruptCheckpointError(
            f"checkpoint {rec.version}: weights file {rec.weights_path} is missing") from None
    except OSError as exc:
        raise CorruptCheckpointError(
            f"checkpoint {rec.version}: cannot read {rec.weights_path}: {exc}") from exc
    found = hashlib.sha256(data).hexdigest()
    if found != rec.weights_sha256:
        raise CorruptCheckpointError(
            f"checkpoint {rec.version}: weights sha256 mismatch: expected {rec.weights_sha256}, "
            f"found {found} ({len(data)} bytes, registered {rec.size_bytes}) in {rec.weights_path}")
    return data


def lasting(exc: CorruptCheckpointError) -> bool:
    """Whether ``read_weights``'s ``exc`` is a verdict on the checkpoint (not its sha256, the file missing,
    pruned) rather than a read that failed and may pass (an I/O error, too many open files, a permission)."""
    return not isinstance(exc.__cause__, OSError)


def raise_unless_lasting(exc: CorruptCheckpointError, doing: str) -> None:
    """``RegistryUnavailableError`` (nothing changed; the same call may succeed later) when ``exc`` is a read
    that failed rather than a verdict on the weights (``lasting``): no model is rejected, skipped or replaced
    for an I/O error that passes."""
    if not lasting(exc):
        raise RegistryUnavailableError(f"cannot {doing} now: {exc} (nothing changed; run it again once the "
                                       "file can be read)") from exc


def read_snapshot(rec: ModelRecord) -> Snapshot | None:
    """The episodes ``rec`` was trained on, from its ``snapshot.json``; None when there is none.

    Raises ``PrunedCheckpointError`` when its files were pruned and ``CorruptCheckpointError`` when the file
    cannot be read or does not hash to the model's snapshot id.
    """
    refuse_pruned(rec)
    path = rec.path / SNAPSHOT_FILE
    try:
        doc = json.loads(path.read_bytes())
        snap = Snapshot.of([(str(i), str(s)) for i, s in doc["episodes"]])
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise CorruptCheckpointError(f"checkpoint {rec.version}: cannot read {path}: {exc.strerror or exc}") from exc
    except (ValueError, KeyError, TypeError, RecursionError) as exc:  # (RecursionError: nested past the parser)
        raise CorruptCheckpointError(f"checkpoint {rec.version}: {path} is not a list of episodes: "
                                     f"{type(exc).__name__}: {exc}") from exc
    if not snap.is_of(rec.snapshot_id):
        raise CorruptCheckpointError(f"checkpoint {rec.version}: the {len(snap.ids)} episodes in {path} are not "
                                     f"its snapshot {rec.snapshot_id} (they hash to {snap.snapshot_id})")
    return snap


def weights_problem(rec: ModelRecord, read: Callable[[ModelRecord], bytes] = read_weights) -> str | None:
    """Why the weights of ``rec`` cannot be served (the error of ``read``, the registry's reader: ``read_weights``
    or what wraps it), or None when they can. A verdict on the bytes is remembered per ``file_state`` for
    ``WEIGHTS_RECHECK_S``; a read that failed (which may pass) is not."""
    state = file_state(rec.weights_path)
    key = None if state is None else (str(rec.weights_path), rec.weights_sha256, rec.pruned_at, *state)
    now = time.monotonic()
    with _CHECKED_LOCK:
        if key in _CHECKED and now - _CHECKED[key][1] < WEIGHTS_RECHECK_S:
            return _CHECKED[key][0]
    try:
        read(rec)
    except CorruptCheckpointError as exc:
        problem, remembered = str(exc), lasting(exc)
    else:
        problem, remembered = None, True
    if key is not None and remembered:
        with _CHECKED_LOCK:
            if len(_CHECKED) >= _CHECKED_MAX:
                _CHECKED.clear()
            _CHECKED[key] = (problem, now)
    return problem
