"""Pruning the registry: which models keep their weights (the champion, the rollback chain, candidates), dry
runs, crashes mid-prune, and prunes that land during a rollback, a promote or another prune."""

from __future__ import annotations

import errno
import math
import os
import shutil
import sqlite3
import threading
import time
from pathlib import Path

import pytest

from storage import pruning
from storage.errors import PrunedCheckpointError, RegistryError
from storage.models import ModelRegistry, ModelStatus
from tests.conftest import failing_prune_claims_of, failing_reads_of
from tests.storage.test_models import _flip_byte, _register


def _history_of_five(reg: ModelRegistry) -> list[str]:
    """a..e promoted in turn (e is champion), then a rejected r and a fresh candidate c."""
    promoted = [_register(reg, mse) for mse in (0.010, 0.008, 0.006, 0.004, 0.002)]
    for v in promoted:
        assert reg.gate(v).promoted
    rejected = _register(reg, 0.5)
    assert not reg.gate(rejected).promoted
    candidate = _register(reg, 0.001)  # registered, not yet gated: a retrain job in flight
    return promoted + [rejected, candidate]


def test_prune_keeps_the_champion_the_rollback_chain_and_candidates(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    before = {v: reg.get(v).size_bytes for v in (a, b, rejected)}
    result = reg.prune(keep=3)
    assert result.kept == [e, d, c] and sorted(result.pruned) == sorted([a, b, rejected])
    assert result.freed_bytes >= sum(before.values())
    assert sorted(p.name for p in reg.models_dir.iterdir()) == sorted([c, d, e, candidate])
    for v in (a, b, rejected):  # the rows, metrics and statuses stay; only the weights are gone
        rec = reg.get(v)
        assert rec.pruned_at is not None and rec.metrics["h1_mse"] > 0
        assert rec.to_json()["pruned_at"] == rec.pruned_at
        with pytest.raises(PrunedCheckpointError, match=f"{v}: weights pruned at"):
            reg.load_weights(v)
        with pytest.raises(PrunedCheckpointError, match=f"{v}: weights pruned at"):
            reg.snapshot(v)  # its files went with the weights
    assert reg.get(a).status is ModelStatus.RETIRED and reg.get(rejected).status is ModelStatus.REJECTED
    assert reg.get(candidate).pruned_at is None and reg.load_weights(candidate)
    assert reg.gate(candidate).promoted  # the job in flight still finishes
    # the chain is now candidate, e, d, c: rolls back three times, then says why it stops
    assert [reg.rollback() for _ in range(3)] == [e, d, c]
    with pytest.raises(RegistryError, match=rf"no previous champion.*{b}.*weights pruned"):
        reg.rollback()
    assert reg.champion() == c


def test_prune_keep_one_keeps_only_the_champion_and_is_idempotent(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    assert sorted(reg.prune(keep=1).pruned) == sorted([a, b, c, d, rejected])
    again = reg.prune(keep=1)
    assert again.pruned == [] and again.freed_bytes == 0 and again.kept == [e]
    assert reg.load_weights(e) and reg.champion() == e


def test_prune_dry_run_changes_nothing(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    before, records = _files(reg.models_dir), [r.to_json() for r in reg.list()]
    result = reg.prune(keep=2, dry_run=True)
    assert sorted(result.pruned) == sorted([a, b, c, rejected]) and result.kept == [e, d]
    assert result.freed_bytes > 0
    assert _files(reg.models_dir) == before and [r.to_json() for r in reg.list()] == records


def _files(root) -> dict[str, bytes]:
    """Every file under ``root``, by path, with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_prune_refuses_a_bad_keep(reg: ModelRegistry) -> None:
    _history_of_five(reg)
    for keep in (0, -1, 1.5, True):
        with pytest.raises(RegistryError, match="keep must be a whole number of at least 1"):
            reg.prune(keep=keep)
    assert all(r.pruned_at is None for r in reg.list())


def test_prune_without_a_champion_keeps_everything_but_rejected(reg: ModelRegistry) -> None:
    bad = _register(reg, math.nan)
    assert not reg.gate(bad).promoted
    fresh = _register(reg, 0.01)
    assert reg.prune(keep=1).pruned == [bad] and reg.load_weights(fresh)


def test_prune_finishes_deleting_what_a_crash_left(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    with sqlite3.connect(reg.db_path) as conn:  # as if a prune committed and died before deleting
        conn.execute("UPDATE models SET pruned_at = '2026-11-21T00:00:00+00:00' WHERE version = ?", (a,))
    result = reg.prune(keep=5)
    assert result.pruned == [a, rejected] and result.kept == [e, d, c, b]
    assert result.freed_bytes > 0 and not reg.get(a).path.exists()


def test_promote_refuses_a_pruned_model(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    reg.prune(keep=2)
    with pytest.raises(PrunedCheckpointError, match="weights pruned"):
        reg.promote(b)
    assert reg.champion() == e


def test_a_prune_that_lands_during_a_rollback_stops_it(reg: ModelRegistry, monkeypatch) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    verify = reg.verify

    def verify_then_prune(version: str) -> None:  # the rollback checked d's weights; then a prune removes them
        verify(version)
        ModelRegistry(reg.data_dir).prune(keep=1)

    monkeypatch.setattr(reg, "verify", verify_then_prune)
    with pytest.raises(RegistryError, match="changed while rolling back"):
        reg.rollback()
    assert reg.champion() == e and reg.get(e).status is ModelStatus.CHAMPION


def test_a_registry_made_before_pruning_existed_is_migrated(tmp_path) -> None:
    from storage.database import DB_NAME, connection, ensure_schema
    from storage.models import _MIGRATIONS
    data = tmp_path / "old"
    data.mkdir()
    with connection(data / DB_NAME, RegistryError) as conn:
        ensure_schema(conn, "models", _MIGRATIONS[:1])
        conn.execute("INSERT INTO models (version, seq, status, reason, parent, snapshot_id, eval_split_hash, "
                     "weights_sha256, size_bytes, created, updated, metrics, config) VALUES "
                     "('m000001-00000000', 1, 'retired', '', NULL, 's', 'h', 'x', 1, 't', 't', '{}', '{}')")
    reg = ModelRegistry(data)
    assert reg.get("m000001-00000000").pruned_at is None
    assert reg.prune(keep=1).pruned == ["m000001-00000000"]


def test_promote_stops_when_a_prune_lands_after_its_check(reg: ModelRegistry, monkeypatch) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    read = reg._read_verified
    calls = []

    def read_then_prune(rec):  # promote checked b's weights; then a prune (another process) removes them
        data = read(rec)
        if not calls:
            calls.append(rec.version)
            ModelRegistry(reg.data_dir).prune(keep=1)
            return data
        return read(reg.get(rec.version))

    monkeypatch.setattr(reg, "_read_verified", read_then_prune)
    with pytest.raises(PrunedCheckpointError, match="weights pruned"):
        reg.promote(b)
    assert calls == [b] and reg.champion() == e and reg.get(b).status is ModelStatus.RETIRED


@pytest.mark.parametrize("damage", ["flip a byte", "delete"])
def test_a_corrupt_model_of_the_chain_does_not_use_up_a_keep_slot(reg: ModelRegistry, damage: str) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        reg.gate(v)
    if damage == "delete":
        reg.get(b).weights_path.unlink()
    else:
        _flip_byte(reg, b)
    result = reg.prune(keep=2)
    assert result.kept == [c, a] and result.pruned == [b]  # b could never be rolled back to
    assert reg.rollback() == a


@pytest.mark.parametrize("code", [errno.EIO, errno.EMFILE, errno.EACCES])
def test_a_read_error_on_a_rollback_target_keeps_it(reg: ModelRegistry, monkeypatch, code: int) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        reg.gate(v)
    failed = failing_reads_of(reg.get(b).weights_path, monkeypatch, code=code)
    result = reg.prune(keep=2)
    assert failed and result.pruned == []
    assert result.kept == [c, b, a]  # b, unread, takes no slot: a is kept too, in case b is damaged after all
    assert reg.get(b).pruned_at is None and reg.load_weights(b)
    again = reg.prune(keep=2)  # b reads now
    assert again.kept == [c, b] and again.pruned == [a]
    assert reg.rollback() == b


def test_two_prunes_at_once_both_finish(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    total = sum(f.stat().st_size for v in (a, b, c, d, rejected) for f in reg.get(v).path.iterdir())
    results, errors = [], []

    def work() -> None:
        try:
            results.append(ModelRegistry(reg.data_dir).prune(keep=1))
        except BaseException as exc:  # noqa: BLE001 - reported by the assert below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    assert set().union(*(r.pruned for r in results)) == {a, b, c, d, rejected}
    assert sum(r.freed_bytes for r in results) == total  # each directory deleted, and counted, once
    assert sorted(p.name for p in reg.models_dir.iterdir()) == sorted([e, candidate])


def test_a_dry_run_also_shows_what_a_crashed_prune_left(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    with sqlite3.connect(reg.db_path) as conn:
        conn.execute("UPDATE models SET pruned_at = '2026-11-21T00:00:00+00:00' WHERE version = ?", (a,))
    dry = reg.prune(keep=5, dry_run=True)
    real = reg.prune(keep=5)
    assert dry.pruned == real.pruned == [a, rejected] and dry.freed_bytes == real.freed_bytes > 0


def test_gating_a_pruned_model_changes_nothing(reg: ModelRegistry) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    reg.prune(keep=1)
    before = reg.get(a)
    decision = reg.gate(a)
    assert not decision.promoted and "not a candidate" in decision.reason
    assert reg.get(a) == before



def test_prune_sweeps_the_dot_folders_crashed_calls_left(reg: ModelRegistry) -> None:
    import os
    import time
    _history_of_five(reg)
    old, fresh = reg.models_dir / ".tmp-crashed", reg.models_dir / ".tmp-live"
    half_deleted = reg.models_dir / ".prune-m000001-abcdef12-0a0b0c0d"
    for d in (old, fresh, half_deleted):
        d.mkdir()
        (d / "weights.pt").write_bytes(b"x" * 100)
    hours_ago = time.time() - 2 * 3600
    for d in (old, half_deleted):
        os.utime(d, (hours_ago, hours_ago))
    reg.prune(keep=5)
    assert not old.exists() and not half_deleted.exists() and fresh.exists()


def test_after_a_rollback_prune_keeps_the_model_rolled_back_from_while_slots_remain(reg: ModelRegistry) -> None:
    a, b, c, d = (_register(reg, mse) for mse in (0.010, 0.008, 0.006, 0.004))
    for v in (a, b, c, d):
        reg.gate(v)
    assert reg.prune(keep=2).kept == [d, c]
    assert reg.rollback() == c  # the chain is now c alone (a and b were pruned)
    result = reg.prune(keep=2)
    assert result.kept == [c, d] and result.pruned == []  # d can still be promoted again by hand
    assert reg.promote(d).promoted


def test_a_corrupt_rolled_back_champion_does_not_take_a_slot_either(reg: ModelRegistry) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        reg.gate(v)
    assert reg.rollback() == b  # c out of service
    _flip_byte(reg, c)
    result = reg.prune(keep=3)
    assert result.kept == [b, a] and result.pruned == [c]


def test_a_model_whose_files_cannot_be_deleted_stays_unpruned_and_usable(reg: ModelRegistry, monkeypatch) -> None:
    """The marks are committed before the deletes: one the prune could not delete, still whole, gets its mark taken
    off again (it was refused by rollback and promote for ever after, its files still there), and is named."""
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    failing_prune_claims_of(monkeypatch, lambda src: src == reg.models_dir / d)
    result = reg.prune(keep=1)
    assert result.kept == [e] and result.pruned == [a, b, c, rejected]
    assert result.not_deleted == {d: f"cannot delete {d}/: {os.strerror(errno.EACCES)}"}
    assert reg.get(d).pruned_at is None and reg.get(d).weights_path.exists() and reg.load_weights(d)
    assert reg.rollback() == d and reg.champion() == d
    monkeypatch.undo()
    assert reg.prune(keep=1).pruned == [e]  # (the folder can be deleted again: the next prune does)


def test_a_mark_a_crashed_prune_left_on_a_folder_that_cannot_be_deleted_is_taken_off(reg, monkeypatch) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    with sqlite3.connect(reg.db_path) as conn:  # as if a prune committed and died before deleting
        conn.execute("UPDATE models SET pruned_at = '2026-11-21T00:00:00+00:00' WHERE version = ?", (d,))
    failing_prune_claims_of(monkeypatch, lambda src: src == reg.models_dir / d)
    result = reg.prune(keep=5)
    assert d in result.not_deleted and d not in result.pruned and reg.get(d).pruned_at is None
    assert reg.load_weights(d)


def test_a_version_folder_that_is_a_link_loses_the_link_not_what_it_points_to(reg: ModelRegistry, tmp_path) -> None:
    """A model moved to another disk and linked back: the prune deletes the link (no ``.prune-*`` link left for
    ever) and leaves the folder it pointed to, which is not the registry's to delete."""
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    elsewhere = tmp_path / "other-disk" / a
    shutil.move(reg.models_dir / a, elsewhere.parent.mkdir() or elsewhere)
    (reg.models_dir / a).symlink_to(elsewhere, target_is_directory=True)
    result = reg.prune(keep=4)
    assert result.pruned == [a, rejected] and result.not_deleted == {}
    assert not os.path.lexists(reg.models_dir / a) and not list(reg.models_dir.glob(".prune-*"))
    assert (elsewhere / "weights.pt").is_file()


def test_a_claim_skips_a_version_whose_mark_another_prune_took_off(reg: ModelRegistry) -> None:
    """Prune P2 read x marked; P1, unable to claim x (another user's read-only models/), took its mark off, and an
    operator promoted x. P2's claim, under the write lock, reads the mark again: it must not delete the champion's
    folder (it did, when the claims were made outside any lock)."""
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    assert reg.promote(a) and reg.champion() == a and reg.get(a).pruned_at is None
    with reg._transaction() as conn:
        claimed, failed = pruning.claim(conn, reg.models_dir, [a], "now", lambda version: True)
    assert claimed == {} and failed == {} and reg.load_weights(a)


def test_a_folder_that_lost_its_weights_and_cannot_be_claimed_stays_pruned(reg: ModelRegistry, monkeypatch) -> None:
    """Marked, its weights gone (a hand removal, an older prune that deleted in place and died): the failed claim
    does not call it usable again."""
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    with sqlite3.connect(reg.db_path) as conn:
        conn.execute("UPDATE models SET pruned_at = '2026-11-21T00:00:00+00:00' WHERE version = ?", (a,))
    reg.get(a).weights_path.unlink()
    failing_prune_claims_of(monkeypatch, lambda src: src == reg.models_dir / a)
    result = reg.prune(keep=5)
    assert a in result.not_deleted and reg.get(a).pruned_at is not None


def test_a_link_is_sized_as_what_a_prune_frees_and_swept_by_its_own_age(reg: ModelRegistry, tmp_path) -> None:
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    elsewhere = tmp_path / "other-disk" / a
    elsewhere.parent.mkdir()
    shutil.move(reg.models_dir / a, elsewhere)
    (reg.models_dir / a).symlink_to(elsewhere, target_is_directory=True)
    dry = reg.prune(keep=4, dry_run=True)
    assert dry.pruned == [a, rejected] and dry.freed_bytes == pruning.tree_size(reg.get(rejected).path)
    left = reg.models_dir / ".prune-gone-0badf00d"  # a crashed prune's claimed link whose target went since
    left.symlink_to(tmp_path / "gone", target_is_directory=True)
    os.utime(left, (1.0, 1.0), follow_symlinks=False)
    assert pruning.sweep_stale(reg.models_dir, time.time()) == [left.name] and not os.path.lexists(left)


def test_a_failed_claim_reads_no_weights_under_the_write_lock(reg: ModelRegistry, monkeypatch) -> None:
    """Whether a model it could not claim is still whole is decided by its file's size, not a sha256 of gigabytes
    read with every other writer (the service's leases and uploads) waiting for the lock."""
    a, b, c, d, e, rejected, candidate = _history_of_five(reg)
    failing_prune_claims_of(monkeypatch, lambda src: src.parent == reg.models_dir and not src.name.startswith("."))
    real, locked = Path.read_bytes, []

    def read_bytes(self: Path) -> bytes:  # (the chain's sha256 checks come before the lock, by design)
        other = sqlite3.connect(reg.db_path, timeout=0)
        try:
            other.execute("BEGIN IMMEDIATE")
            other.rollback()
        except sqlite3.OperationalError:
            locked.append(self)
        finally:
            other.close()
        return real(self)
    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    result = reg.prune(keep=1)
    assert sorted(result.not_deleted) == [a, b, c, d, rejected] and locked == []
    monkeypatch.undo()
    assert all(reg.get(v).pruned_at is None for v in (a, b, c, d, rejected))
    reg.get(a).weights_path.write_bytes(b"cut short")  # another size: not whole, stays marked
    failing_prune_claims_of(monkeypatch, lambda src: src == reg.models_dir / a)
    assert a in reg.prune(keep=1).not_deleted and reg.get(a).pruned_at is not None
