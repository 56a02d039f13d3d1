"""The model registry: round trips, the promotion gate, rollback, corrupt checkpoints (real SQLite files)."""

from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import sqlite3
import threading
from pathlib import Path

import pytest

from storage.errors import CorruptCheckpointError, RegistryError, RegistryUnavailableError
from storage.gate import GateDecision
from storage.models import ModelRegistry, ModelStatus
from storage.rows import Snapshot
from tests.conftest import failing_reads_of

SPLIT = "split-aaaa"


def _metrics(h1_mse: float, **extra: float) -> dict:
    return {"h1_mse": h1_mse, "h1_psnr": 20.0, "h5_mse": 2 * h1_mse, "baseline_h1_mse": 0.05, **extra}


def _register(reg: ModelRegistry, h1_mse: float, *, split: str = SPLIT, weights: bytes | None = None,
              parent: str | None = None, **extra: float) -> str:
    weights = weights if weights is not None else f"weights {h1_mse} {extra}".encode() * 10
    return reg.register(weights, {"members": 2, "image_size": 16}, _metrics(h1_mse, **extra),
                        snapshot_id="snap-1", eval_split_hash=split, parent=parent)


def _flip_byte(reg: ModelRegistry, version: str) -> None:
    path = reg.get(version).weights_path
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def test_a_model_keeps_the_episodes_it_was_trained_on(reg: ModelRegistry) -> None:
    snap = Snapshot.of([("ep-a", "1" * 64), ("ep-b", "2" * 64)])
    version = reg.register(b"weights", {}, _metrics(0.1), snap.snapshot_id, SPLIT, snapshot=snap)
    assert reg.snapshot(version) == snap
    assert reg.snapshot(_register(reg, 0.2)) is None  # registered without its episodes
    path = reg.get(version).path / "snapshot.json"
    doc = json.loads(path.read_text())
    for damage in (b"{", json.dumps({**doc, "episodes": doc["episodes"][:1]}).encode(),
                   json.dumps({**doc, "episodes": doc["episodes"][::-1]}).encode(), b'{"episodes": [["a"]]}',
                   b"[" * 100_000):  # (nested past the JSON parser's recursion limit)
        path.write_bytes(damage)
        with pytest.raises(CorruptCheckpointError, match=f"checkpoint {version}: .*snapshot.json"):
            reg.snapshot(version)
    path.write_text(json.dumps(doc))
    assert reg.snapshot(version) == snap


def test_register_refuses_episodes_that_are_not_its_snapshot(reg: ModelRegistry) -> None:
    snap = Snapshot.of([("ep-a", "1" * 64), ("ep-b", "2" * 64)])
    unsorted = Snapshot.of([("ep-b", "2" * 64), ("ep-a", "1" * 64)])
    for given, snapshot_id in ((snap, "snap-1"), (unsorted, unsorted.snapshot_id),
                               (Snapshot(snap.ids, snap.snapshot_id, snap.sha256s[:1]), snap.snapshot_id)):
        with pytest.raises(RegistryError, match="episodes given are not snapshot"):
            reg.register(b"weights", {}, _metrics(0.1), snapshot_id, SPLIT, snapshot=given)
    assert reg.list() == [] and [p.name for p in reg.models_dir.iterdir()] == []


def test_resolve_takes_a_version_or_a_unique_prefix(reg: ModelRegistry) -> None:
    versions = [_register(reg, h) for h in (0.1, 0.2)]
    for version in versions:
        assert reg.resolve(version).version == version
        assert reg.resolve(version.split("-")[0]).version == version
    with pytest.raises(RegistryError, match=f"prefix 'm0' is ambiguous \\({versions[0]}, {versions[1]}\\)"):
        reg.resolve("m0")
    for unknown in ("", "m000003", "M000001", "%", "m00000_"):  # LIKE's wildcards are plain characters here
        with pytest.raises(RegistryError, match="unknown model version"):
            reg.resolve(unknown)


def test_register_and_load_round_trip(reg: ModelRegistry) -> None:
    weights = bytes(range(256)) * 7
    version = reg.register(weights, {"members": 3}, {"h1_mse": 0.01, "note": "x"}, "snap-9", SPLIT)
    assert reg.load_weights(version) == weights
    rec = reg.get(version)
    assert rec.status is ModelStatus.CANDIDATE and rec.reason == ""
    assert rec.config == {"members": 3} and rec.metrics == {"h1_mse": 0.01, "note": "x"}
    assert (rec.snapshot_id, rec.eval_split_hash, rec.parent) == ("snap-9", SPLIT, None)
    assert rec.weights_sha256 == hashlib.sha256(weights).hexdigest() and rec.size_bytes == len(weights)
    meta = json.loads((rec.path / "meta.json").read_text())
    assert meta["weights_sha256"] == rec.weights_sha256 and meta["snapshot_id"] == "snap-9"
    assert json.loads((rec.path / "config.json").read_text()) == {"members": 3}
    assert json.loads((rec.path / "metrics.json").read_text())["h1_mse"] == 0.01
    assert not [p for p in reg.models_dir.iterdir() if p.name.startswith(".tmp")]
    assert reg.champion() is None
    # A second registry on the same directory sees the same rows (they are in catalog.sqlite).
    again = ModelRegistry(reg.data_dir)
    assert again.get(version) == rec
    with sqlite3.connect(reg.data_dir / "catalog.sqlite") as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_versions_are_unique_and_sort_in_registration_order(reg: ModelRegistry) -> None:
    versions = [_register(reg, 0.1, weights=b"same weights") for _ in range(3)]
    versions.append(_register(reg, 0.1, weights=b"other"))
    assert len(set(versions)) == 4 and versions == sorted(versions)
    assert [r.version for r in reg.list()] == versions


def test_register_refuses_bad_input(reg: ModelRegistry) -> None:
    with pytest.raises(RegistryError, match="non-empty bytes"):
        reg.register(b"", {}, {}, "snap", SPLIT)
    with pytest.raises(RegistryError, match="JSON-serialisable"):
        reg.register(b"w", {"x": object()}, {}, "snap", SPLIT)
    with pytest.raises(RegistryError, match="eval_split_hash"):
        reg.register(b"w", {}, {}, "snap", "")
    with pytest.raises(RegistryError, match="unknown model version 'nope'"):
        reg.register(b"w", {}, {}, "snap", SPLIT, parent="nope")
    assert reg.list() == [] and list(reg.models_dir.iterdir()) == []


def test_get_unknown_version_says_so(reg: ModelRegistry) -> None:
    with pytest.raises(RegistryError, match="unknown model version 'm9'; the registry is empty"):
        reg.get("m9")


def test_first_model_becomes_champion(reg: ModelRegistry) -> None:
    v = _register(reg, 0.02)
    decision = reg.gate(v, eval_split_hash=SPLIT)
    assert isinstance(decision, GateDecision) and decision.promoted
    assert "first champion" in decision.reason and decision.champion_before is None
    assert reg.champion() == v and reg.get(v).status is ModelStatus.CHAMPION


def test_first_model_with_nan_or_wrong_split_is_refused(reg: ModelRegistry) -> None:
    nan = _register(reg, math.nan)
    d = reg.gate(nan, eval_split_hash=SPLIT)
    assert not d.promoted and "not finite" in d.reason and "h1_mse" in d.reason
    strict = json.loads((reg.get(nan).path / "metrics.json").read_text(), parse_constant=pytest.fail)  # (jq's way)
    assert strict["h1_mse"] is None and math.isnan(reg.get(nan).metrics["h1_mse"])  # the row keeps it for the gate
    wrong = _register(reg, 0.01, split="split-other")
    d = reg.gate(wrong, eval_split_hash=SPLIT)
    assert not d.promoted and "wrong eval split" in d.reason
    assert reg.champion() is None


def test_gate_promotes_better_and_refuses_worse_nan_and_wrong_split(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.010)
    assert reg.gate(champ).promoted
    worse = _register(reg, 0.012)
    barely = _register(reg, 0.0099)  # 1% better: below the default 2% bar
    nan = _register(reg, 0.005, h1_psnr=math.inf)
    wrong = _register(reg, 0.001, split="split-bbbb")
    for version, words in ((worse, "not better enough"), (barely, "not better enough"),
                           (nan, "h1_psnr is not finite"), (wrong, "wrong eval split")):
        d = reg.gate(version)
        assert not d.promoted and words in d.reason, d.reason
        rec = reg.get(version)
        assert rec.status is ModelStatus.REJECTED and rec.reason == d.reason
        assert reg.load_weights(version)  # rejected candidates are kept
    assert reg.champion() == champ

    better = _register(reg, 0.008, parent=champ)
    d = reg.gate(better)
    assert d.promoted and d.champion_before == champ and d.champion_value == 0.010
    assert d.candidate_value == 0.008 and "-" not in d.reason.split("(")[1][:2]
    assert reg.champion() == better
    assert reg.get(champ).status is ModelStatus.RETIRED
    assert [e.version for e in reg.history()] == [champ, better]
    assert len(reg.list(ModelStatus.REJECTED)) == 4


def test_gate_uses_the_given_current_split_over_the_champions(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.010)
    reg.gate(champ)
    cand = _register(reg, 0.001)
    d = reg.gate(cand, eval_split_hash="split-new")
    assert not d.promoted and "current eval split is split-new" in d.reason


def test_gate_threshold_is_configurable(reg: ModelRegistry) -> None:
    reg.gate(_register(reg, 0.010))
    tie = _register(reg, 0.010)
    decision = reg.gate(tie, min_rel_improvement=0.0)  # (no better is not better, even with no bar)
    assert not decision.promoted and decision.reason.startswith("not better enough"), decision
    barely = _register(reg, 0.0099)
    assert reg.gate(barely, min_rel_improvement=0.0).promoted
    with pytest.raises(RegistryError, match="min_rel_improvement"):
        reg.gate(barely, min_rel_improvement=1.5)


def test_gate_refuses_a_corrupt_candidate(reg: ModelRegistry) -> None:
    reg.gate(_register(reg, 0.010))
    cand = _register(reg, 0.001)
    _flip_byte(reg, cand)
    d = reg.gate(cand)
    assert not d.promoted and "corrupt checkpoint" in d.reason and "sha256 mismatch" in d.reason
    assert reg.get(cand).status is ModelStatus.REJECTED


def test_corrupt_checkpoint_is_refused_on_load_and_promote(reg: ModelRegistry) -> None:
    v = _register(reg, 0.01)
    _flip_byte(reg, v)
    with pytest.raises(CorruptCheckpointError, match=f"checkpoint {v}: weights sha256 mismatch: expected"):
        reg.load_weights(v)
    with pytest.raises(CorruptCheckpointError, match="sha256 mismatch"):
        reg.promote(v)
    assert reg.champion() is None
    reg.get(v).weights_path.unlink()
    with pytest.raises(CorruptCheckpointError, match="is missing"):
        reg.load_weights(v)


def test_promote_overrides_metrics_but_not_the_split(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.010)
    reg.gate(champ)
    worse = _register(reg, 0.5)
    assert reg.gate(worse).promoted is False
    d = reg.promote(worse)
    assert d.promoted and reg.champion() == worse and reg.get(worse).reason == "promoted by the operator"
    assert reg.promote(worse).promoted is False  # already champion
    wrong = _register(reg, 0.001, split="split-bbbb")
    with pytest.raises(RegistryError, match="evaluated on eval split split-bbbb"):
        reg.promote(wrong)
    assert reg.champion() == worse


def test_a_gate_after_an_operator_promoted_its_candidate_says_promoted(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.010)
    reg.gate(champ)
    cand = _register(reg, 0.5)
    reg.promote(cand)  # between the job's register and its gate (the job then recorded 'rejected')
    d = reg.gate(cand)
    assert d.promoted and d.champion_before == champ and "promoted by the operator" in d.reason


@pytest.mark.parametrize("metrics", [{"h1_mse": math.nan}, {"h1_psnr": math.inf}])
def test_promote_refuses_a_model_whose_training_diverged(reg: ModelRegistry, metrics) -> None:
    """The operator's override of the metrics still wants numbers: a diverged model's scores rank nothing."""
    champ = _register(reg, 0.010)
    reg.gate(champ)
    mse = metrics.pop("h1_mse", 0.001)
    nan = _register(reg, mse, **metrics)
    assert not reg.gate(nan).promoted
    with pytest.raises(RegistryError, match=f"refusing to promote {nan}: h1_.* is not finite .*: its training "
                                            "diverged"):
        reg.promote(nan)
    assert reg.champion() == champ and reg.get(nan).status is ModelStatus.REJECTED


def test_rollback_restores_the_previous_champion(reg: ModelRegistry) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        assert reg.gate(v).promoted
    assert reg.rollback() == b
    assert reg.champion() == b and reg.get(b).status is ModelStatus.CHAMPION
    assert reg.get(c).status is ModelStatus.RETIRED and "rolled back" in reg.get(c).reason
    assert reg.rollback() == a
    with pytest.raises(RegistryError, match="no previous champion"):
        reg.rollback()
    assert reg.champion() == a
    assert [e.rolled_back_at is None for e in reg.history()] == [True, False, False]


def test_gate_does_not_rejudge_a_rolled_back_or_rejected_model(reg: ModelRegistry) -> None:
    a, b = _register(reg, 0.010), _register(reg, 0.008)
    assert reg.gate(a).promoted and reg.gate(b).promoted
    assert reg.rollback() == a  # b was taken out of service: its better metric must not bring it back
    decision = reg.gate(b)
    assert not decision.promoted and "retired, not a candidate" in decision.reason
    assert reg.champion() == a and reg.get(b).status is ModelStatus.RETIRED and "rolled back" in reg.get(b).reason
    worse = _register(reg, 0.5)
    assert not reg.gate(worse).promoted and reg.get(worse).status is ModelStatus.REJECTED
    assert "rejected, not a candidate" in reg.gate(worse).reason
    assert reg.promote(b).promoted  # the operator's override still can


def test_reject_candidates_marks_only_the_candidates(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.5)
    assert reg.gate(champ).promoted
    worse = _register(reg, 0.9)
    assert not reg.gate(worse).promoted
    left = [_register(reg, 0.1), _register(reg, 0.2)]
    assert reg.reject_candidates("abandoned") == left
    for version in left:
        assert (reg.get(version).status, reg.get(version).reason) == (ModelStatus.REJECTED, "abandoned")
    assert reg.get(champ).status is ModelStatus.CHAMPION and reg.get(worse).reason != "abandoned"
    assert reg.reject_candidates("again") == [] and reg.champion() == champ
    assert reg.promote(left[0]).promoted  # the operator may still take one


def test_rollback_skips_a_corrupt_previous_champion(reg: ModelRegistry) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        reg.gate(v)
    _flip_byte(reg, b)
    _flip_byte(reg, a)
    with pytest.raises(RegistryError, match=r"no previous champion.*skipped: .*weights unusable.*sha256 mismatch"):
        reg.rollback()
    assert reg.champion() == c  # nothing changed
    reg.get(a).weights_path.write_bytes(f"weights {0.010} {{}}".encode() * 10)  # repaired
    assert reg.rollback() == a
    assert reg.get(b).status is ModelStatus.RETIRED
    with pytest.raises(RegistryError, match="no previous champion"):
        reg.rollback()


def test_rollback_without_champion(reg: ModelRegistry) -> None:
    with pytest.raises(RegistryError, match="nothing has been promoted"):
        reg.rollback()


def test_rollback_after_re_promotion_walks_the_history(reg: ModelRegistry) -> None:
    a, b = _register(reg, 0.010), _register(reg, 0.008)
    reg.gate(a)
    reg.gate(b)
    reg.promote(a)  # history: a, b, a
    assert reg.rollback() == b
    assert reg.rollback() == a
    with pytest.raises(RegistryError):
        reg.rollback()


def test_concurrent_registers_get_distinct_versions(reg: ModelRegistry) -> None:
    versions: list[str] = []
    errors: list[BaseException] = []

    def work(i: int) -> None:
        try:
            versions.append(ModelRegistry(reg.data_dir).register(
                f"w{i}".encode(), {}, {"h1_mse": 0.1}, "snap", SPLIT))
        except BaseException as exc:  # noqa: BLE001 - reported by the assert below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(set(versions)) == 4
    assert sorted(versions) == [r.version for r in reg.list()]


def test_record_to_json_is_strict_json(reg: ModelRegistry) -> None:
    v = reg.register(b"w", {}, {"h1_mse": math.nan, "curve": [1.0, math.inf], "name": "x"}, "snap", SPLIT)
    assert reg.get(v).metrics["h1_mse"] != reg.get(v).metrics["h1_mse"]  # NaN kept in the record
    text = json.dumps(reg.get(v).to_json(), allow_nan=False)
    assert json.loads(text)["metrics"] == {"h1_mse": None, "curve": [1.0, None], "name": "x"}


def test_register_replaces_a_directory_left_by_a_crash(reg: ModelRegistry) -> None:
    weights = b"crashed before commit"
    orphan = reg.models_dir / f"m000001-{hashlib.sha256(weights).hexdigest()[:8]}"
    orphan.mkdir()
    (orphan / "weights.pt").write_bytes(b"half")
    version = reg.register(weights, {}, {"h1_mse": 0.1}, "snap", SPLIT)
    assert version == orphan.name and reg.load_weights(version) == weights
    assert sorted(p.name for p in reg.models_dir.iterdir()) == [version]


# -- retention: prune ---------------------------------------------------------------------------


def test_a_champion_with_damaged_weights_is_replaced_by_the_next_sound_candidate(reg: ModelRegistry) -> None:
    champ = _register(reg, 0.1)
    assert reg.gate(champ).promoted
    _flip_byte(reg, champ)  # a disk error: its metrics still look unbeatable
    worse = _register(reg, 0.5)
    decision = reg.gate(worse)
    assert decision.promoted and reg.champion() == worse, decision
    assert f"replaces champion {champ}, whose weights are unusable" in decision.reason and "sha256" in decision.reason
    assert not reg.gate(_register(reg, 0.5, split="another-split")).promoted  # the split still has to match
    assert not reg.gate(_register(reg, 0.9)).promoted  # and a sound champion is judged as before


def test_a_read_error_on_a_candidate_leaves_it_a_candidate(reg: ModelRegistry, monkeypatch) -> None:
    champ = _register(reg, 0.1)
    assert reg.gate(champ).promoted
    cand = _register(reg, 0.05)
    failed = failing_reads_of(reg.get(cand).weights_path, monkeypatch)
    with pytest.raises(RegistryUnavailableError, match=f"cannot gate {cand} now"):
        reg.gate(cand)
    assert failed and reg.get(cand).status == ModelStatus.CANDIDATE and reg.champion() == champ
    assert reg.gate(cand).promoted  # judged once it reads


def test_a_read_error_on_the_champion_does_not_let_a_worse_candidate_replace_it(reg, monkeypatch) -> None:
    champ = _register(reg, 0.1)
    assert reg.gate(champ).promoted
    worse = _register(reg, 0.5)
    failed = failing_reads_of(reg.get(champ).weights_path, monkeypatch)
    with pytest.raises(RegistryUnavailableError, match=f"against champion {champ}"):
        reg.gate(worse)
    assert failed and reg.champion() == champ and reg.get(worse).status == ModelStatus.CANDIDATE
    assert not reg.gate(worse).promoted  # judged on its metrics once the champion reads


def test_a_read_error_on_the_rollback_target_changes_nothing(reg: ModelRegistry, monkeypatch) -> None:
    a, b, c = (_register(reg, mse) for mse in (0.010, 0.008, 0.006))
    for v in (a, b, c):
        assert reg.gate(v).promoted
    failed = failing_reads_of(reg.get(b).weights_path, monkeypatch)
    with pytest.raises(RegistryUnavailableError, match=f"roll back past {b}"):
        reg.rollback()
    assert failed and reg.champion() == c and reg.get(a).status == ModelStatus.RETIRED
    assert reg.rollback() == b  # not past it to a


def test_every_read_of_the_weights_goes_through_one_reader(reg: ModelRegistry, monkeypatch) -> None:
    """weights_problem reads through _read_verified like load_weights and verify (the seam test_pruning wraps)."""
    version = _register(reg, 0.1)
    read, seen = reg._read_verified, []
    monkeypatch.setattr(reg, "_read_verified", lambda rec: (seen.append(rec.version), read(rec))[1])
    assert reg.weights_problem(version) is None and reg.load_weights(version)
    reg.verify(version)
    assert seen == [version] * 3


def test_check_ready_says_before_a_job_trains_that_models_cannot_take_a_checkpoint(reg: ModelRegistry,
                                                                                    monkeypatch) -> None:
    champion = _register(reg, 0.01)
    reg.gate(champion)
    reg.check_ready()
    assert not list(reg.models_dir.glob(".tmp-*"))  # (its probe gone)
    real = Path.mkdir

    def mkdir(self: Path, *args, **kw) -> None:
        if self.parent == reg.models_dir:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        real(self, *args, **kw)
    monkeypatch.setattr(Path, "mkdir", mkdir)
    with pytest.raises(RegistryUnavailableError, match="cannot store a checkpoint in .* now: Read-only file system"):
        reg.check_ready()
    monkeypatch.undo()
    failing_reads_of(reg.get(champion).weights_path, monkeypatch)
    with pytest.raises(RegistryUnavailableError, match=f"cannot read champion {champion}, which the gate"):
        reg.check_ready()
    _flip_byte(reg, champion)
    reg.check_ready()  # damaged for good: the gate replaces it, so a job may go on


@pytest.mark.parametrize("column, value, message", [
    ("metrics", "not json", "metrics is not a JSON object ('not json')"),
    ("config", "[]", "config is not a JSON object ('[]')"),
    ("status", "weird", "status 'weird' is none of candidate, champion, retired, rejected"),
])
def test_a_row_the_registry_did_not_write_is_refused_naming_it(reg: ModelRegistry, column, value, message) -> None:
    """A hand edit or a damaged file: a RegistryError naming the version and the column (one line from the CLI),
    not a JSONDecodeError or a ValueError from deep inside."""
    version = _register(reg, 0.01)
    with sqlite3.connect(reg.db_path) as conn:
        conn.execute(f"UPDATE models SET {column} = ? WHERE version = ?", (value, version))
    for call in (reg.list, lambda: reg.get(version)):
        with pytest.raises(RegistryError) as info:
            call()
        assert str(info.value) == f"registry row {version}: {message}"


def test_an_alias_that_names_no_model_is_no_champion_and_the_next_gate_repairs_it(reg: ModelRegistry) -> None:
    """A row deleted by hand (the file does not enforce the alias's reference): every command failed on "unknown
    model version", promote included, and only a rollback got out, leaving two rows marked champion."""
    a = _register(reg, 0.01)
    reg.gate(a)
    with sqlite3.connect(reg.db_path) as conn:
        conn.execute("UPDATE model_aliases SET version = 'm999999-deadbeef'")
    assert reg.champion() is None and [m.version for m in reg.list()] == [a]
    b = _register(reg, 0.02)  # worse than a: promoted all the same, as the first champion is
    assert reg.gate(b).promoted and reg.champion() == b
    assert [m.version for m in reg.list(status="champion")] == [b] and reg.get(a).status is ModelStatus.RETIRED
    assert reg.promote(a) and reg.champion() == a and [m.version for m in reg.list(status="champion")] == [a]


def test_rollback_skips_a_champion_evaluated_on_another_eval_split(reg: ModelRegistry) -> None:
    """``promote`` refuses a model measured on another split than the pinned one; ``rollback`` returned to it."""
    old = _register(reg, 0.01, split="split-old")
    assert reg.promote(old, eval_split_hash="split-old").promoted
    a = _register(reg, 0.02)
    assert reg.promote(a, eval_split_hash=SPLIT).promoted  # the split was made again: promoted by hand
    b = _register(reg, 0.01)
    assert reg.gate(b).promoted
    assert reg.rollback(eval_split_hash=SPLIT) == a
    with pytest.raises(RegistryError, match=f"skipped: {old} \\(evaluated on another eval split, split-old\\)"):
        reg.rollback(eval_split_hash=SPLIT)
    assert reg.champion() == a
    # the split made again once more: a model of the new one is not comparable with the champion of the last
    again = _register(reg, 0.001, split="split-new")
    d = reg.gate(again, eval_split_hash="split-new")
    assert not d.promoted and d.reason.endswith(f"promote {again} by hand (models promote) if it should serve")


def test_newest_is_the_model_registered_last(reg: ModelRegistry) -> None:
    """What the dashboard's "last retrain" shows when its process ran none: one row, not the whole registry."""
    assert reg.newest() is None
    a, b = _register(reg, 0.01), _register(reg, 0.02)
    reg.gate(b)
    assert reg.newest().version == b and reg.newest().status is ModelStatus.CHAMPION and a != b
