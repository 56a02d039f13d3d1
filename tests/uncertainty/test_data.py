import dataclasses

import numpy as np
import pytest

import storage.eval_split
from storage.catalog import Catalog
from storage.models import ModelRegistry
from tests.uncertainty.conftest import TINY
from tests.uncertainty.synth import make_episode
from uncertainty.data import action_stats, build_windows, load_eval, load_train, member_indices
from uncertainty.errors import DataError
from uncertainty.model import PredictorConfig
from uncertainty.train import TrainConfig, train_candidate

CFG = PredictorConfig(image_size=16, context=2)


def test_windows_line_up_context_action_and_next_frame():
    eps = [make_episode(0, steps=6), make_episode(1, steps=5)]
    w = build_windows(eps, CFG, horizon=2)
    assert len(w) == 3 + 2 and w.horizon == 2
    ctx, act, tgt = w.batch(np.arange(len(w)), "cpu")
    i = 4  # second episode, step 2
    assert (w.episode[i], w.step[i]) == (1, 2)
    ep = eps[1]
    np.testing.assert_array_equal((ctx[i] * 255).round().byte().permute(0, 2, 3, 1).numpy(), ep.frames[1:3])
    np.testing.assert_array_equal(act[i].numpy(), ep.actions[2:4])
    np.testing.assert_array_equal((tgt[i] * 255).round().byte().permute(0, 2, 3, 1).numpy(), ep.frames[3:5])


def test_windows_refuse_wrong_size_and_too_short_episodes():
    with pytest.raises(DataError, match="frames must be"):
        build_windows([make_episode(0, size=32)], CFG)
    with pytest.raises(DataError, match="long enough"):
        build_windows([make_episode(0, steps=2)], CFG, horizon=1)


def test_bootstrap_draws_whole_episodes_and_is_seeded():
    w = build_windows([make_episode(s, steps=6) for s in range(5)], CFG)
    a = member_indices(w, 3, True, np.random.default_rng(0))
    b = member_indices(w, 3, True, np.random.default_rng(0))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    for idx in a:
        counts = np.bincount(w.episode[idx], minlength=5)
        assert set(counts.tolist()) <= {0, 4, 8, 12, 16, 20}  # 4 windows per drawn episode
    assert all(len(i) == len(w) for i in member_indices(w, 2, False, np.random.default_rng(0)))


def test_bootstrap_never_leaves_a_member_without_windows():
    """Episodes too short for a window are not drawn: a member's pool is never empty (it trained on window 0)."""
    w = build_windows([make_episode(0, steps=12)] + [make_episode(s, steps=2) for s in range(1, 6)], CFG)
    for seed in range(20):
        pools = member_indices(w, 3, True, np.random.default_rng(seed))
        assert all(len(p) == len(w) for p in pools)  # the one episode with windows, drawn every time


def test_action_stats():
    mean, std = action_stats([make_episode(s) for s in range(3)])
    assert mean.shape == std.shape == (2,) and np.all(std > 1)


def test_train_and_eval_splits_never_mix(tmp_path):
    cat = Catalog(tmp_path)
    train_ids = {cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(3)}
    eval_ids = {cat.add_episode(make_episode(10 + s, steps=5), split="eval").episode_id for s in range(2)}
    with pytest.raises(DataError, match="no eval split .*`activecollect eval-split create`"):  # a command to run
        load_eval(cat)
    cat.pin_eval_split(sorted(eval_ids))
    train = load_train(cat)
    episodes, split_hash = load_eval(cat)
    assert set(train.episode_ids) == train_ids
    assert {e.meta.episode_id for e in train.episodes} == train_ids
    assert {e.meta.episode_id for e in episodes} == eval_ids and split_hash == cat.eval_split().hash
    assert train.snapshot_id == cat.snapshot().snapshot_id


def test_empty_train_split_is_refused(tmp_path):
    with pytest.raises(DataError, match="no train episodes"):
        load_train(Catalog(tmp_path))


def test_a_lost_or_damaged_train_file_is_quarantined_and_training_goes_on(tmp_path):
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(4))
    full = cat.snapshot()
    cat.get(ids[0]).path.unlink()
    damaged = cat.get(ids[2]).path
    damaged.write_bytes(damaged.read_bytes()[:-3])
    train = load_train(cat)
    assert train.episode_ids == [ids[1], ids[3]] and len(train.episodes) == 2
    assert train.quarantined == [ids[0], ids[2]]
    assert train.snapshot_id == cat.snapshot().snapshot_id == full.without([ids[0], ids[2]]).snapshot_id
    reasons = {r.episode_id: r.quarantined for r in cat.list(quarantined=True)}
    assert reasons[ids[0]].startswith("found by a training job: ") and "is missing" in reasons[ids[0]]
    assert "sha256 is" in reasons[ids[2]]
    assert load_train(cat).quarantined == []  # the next job finds them out already


def test_max_episodes_counts_only_the_episodes_loaded(tmp_path):
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(3))
    cat.get(ids[0]).path.unlink()
    train = load_train(cat, max_episodes=2)
    assert train.episode_ids == ids[1:]
    assert train.snapshot.ids == ids[1:] and train.snapshot_id == cat.snapshot().snapshot_id  # what was loaded


def test_the_snapshot_names_only_the_episodes_loaded(tmp_path):
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(3))
    train = load_train(cat, max_episodes=2)
    assert train.snapshot.ids == ids[:2] and train.snapshot.sha256s == [cat.get(i).sha256 for i in ids[:2]]
    assert train.snapshot_id != cat.snapshot().snapshot_id


def test_when_every_train_file_is_lost_the_job_says_so(tmp_path):
    cat = Catalog(tmp_path)
    lost = cat.add_episode(make_episode(0, steps=5))
    lost.path.unlink()
    with pytest.raises(DataError, match="the files of all 1 train episodes are missing or damaged"):
        load_train(cat)
    assert cat.count(quarantined=True) == 1


def test_when_most_train_files_are_gone_nothing_is_quarantined(tmp_path):
    cat = Catalog(tmp_path)
    rows = [cat.add_episode(make_episode(s, steps=5)) for s in range(4)]
    for row in rows[:3]:  # e.g. the disk holding episodes/ is not mounted
        row.path.unlink()
    with pytest.raises(DataError, match="the files of 3 of 4 train episodes are missing or damaged .* "
                                        "nothing was quarantined"):
        load_train(cat)
    assert cat.count(quarantined=True) == 0



def copy_in_an_old_catalog(monkeypatch, cat: Catalog, ep, episode_id: str) -> str:
    """Index ``ep`` again under ``episode_id``, as train, as a catalog made before ingests refused replays of
    eval episodes did."""
    with monkeypatch.context() as m:
        m.setattr(storage.eval_split, "refuse_replay", lambda conn, meta, split: None, raising=False)
        copy = dataclasses.replace(ep, meta=dataclasses.replace(ep.meta, episode_id=episode_id))
        return cat.add_episode(copy).episode_id


def test_a_train_copy_of_an_eval_episode_an_old_catalog_holds_is_left_out_and_reported(tmp_path, monkeypatch,
                                                                                       caplog):
    """Training leaves the copy out (so the model is not measured on what it trained on) and says so."""
    cat = Catalog(tmp_path)
    ev = make_episode(10, steps=5)
    cat.add_episode(ev, split="eval")
    cat.pin_eval_split([ev.meta.episode_id])
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(2))
    copy = copy_in_an_old_catalog(monkeypatch, cat, ev, "c0ffee" * 5 + "00")
    assert copy in cat.snapshot().ids
    with caplog.at_level("WARNING", logger="uncertainty.data"):
        train = load_train(cat)
    assert train.episode_ids == ids and [e.meta.episode_id for e in train.episodes] == ids
    assert train.replays == {copy: ev.meta.episode_id}
    assert train.snapshot_id == cat.snapshot().without([copy]).snapshot_id
    assert train.warnings == [caplog.records[-1].getMessage()]
    assert f"left out 1 train episode(s) that replay eval episodes: {copy} (of {ev.meta.episode_id})" in caplog.text
    assert cat.count(quarantined=True) == 0  # left out, not moved: the operator decides
    assert load_train(cat, max_episodes=1).episode_ids == ids[:1]  # counts the episodes loaded, not those left out


def test_a_train_split_of_nothing_but_eval_copies_is_refused(tmp_path, monkeypatch):
    cat = Catalog(tmp_path)
    ev = make_episode(10, steps=5)
    cat.add_episode(ev, split="eval")  # not pinned yet: still the eval split's, once pinned
    copy_in_an_old_catalog(monkeypatch, cat, ev, "ab" * 16)
    with pytest.raises(DataError, match=r"every train episode \(1\) replays an eval episode"):
        load_train(cat)


def test_a_retrain_on_an_old_catalog_with_an_eval_copy_trains_without_it_and_says_so(tmp_path, monkeypatch):
    cat = Catalog(tmp_path)
    ev = make_episode(10, steps=6)
    cat.add_episode(ev, split="eval")
    cat.pin_eval_split([ev.meta.episode_id])
    ids = sorted(cat.add_episode(make_episode(s, steps=6)).episode_id for s in range(2))
    copy = copy_in_an_old_catalog(monkeypatch, cat, ev, "c0ffee" * 5 + "00")
    registry = ModelRegistry(tmp_path)
    result = train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert result.metrics["train_episodes"] == 2 and result.metrics["train_replays_left_out"] == 1
    assert registry.snapshot(result.version).ids == ids  # what it was trained on
    assert any(f"{copy} (of {ev.meta.episode_id})" in line for line in result.warnings)  # retrain --json's


def test_an_episode_the_operator_quarantines_while_a_job_loads_is_not_reported_as_damaged(tmp_path):
    """`episodes quarantine` beside a running retrain: the file it moves aside is missing where the job's
    snapshot said, but it is the operator's quarantine, not a lost file the job found and quarantined."""
    ids = sorted(Catalog(tmp_path).add_episode(make_episode(s, steps=5)).episode_id for s in range(4))

    class OperatorMeanwhile(Catalog):  # a real catalog; a second one (the operator's command) acts between reads
        def load(self, episode_id):
            if episode_id == ids[0] and not self.get(ids[0]).quarantined:
                Catalog(tmp_path).quarantine(ids[0], "operator: bad lighting")
            return super().load(episode_id)

    train = load_train(OperatorMeanwhile(tmp_path))
    assert train.quarantined == [] and train.episode_ids == ids[1:]
    row = Catalog(tmp_path).get(ids[0])
    assert row.quarantined == "operator: bad lighting"


def test_most_train_episodes_quarantined_by_the_operator_while_a_job_loads_is_no_unmounted_disk(tmp_path):
    """An operator who quarantines a bad batch (most of the train split) beside a running retrain: the job trains
    on what is left; it does not fail saying the data directory's disk looks unmounted."""
    ids = sorted(Catalog(tmp_path).add_episode(make_episode(s, steps=5)).episode_id for s in range(4))

    class OperatorMeanwhile(Catalog):
        def load(self, episode_id):
            if not self.get(ids[1]).quarantined:
                for other in ids[1:]:
                    Catalog(tmp_path).quarantine(other, "operator: bad batch")
            return super().load(episode_id)

    train = load_train(OperatorMeanwhile(tmp_path))
    assert train.episode_ids == ids[:1] and train.quarantined == []
