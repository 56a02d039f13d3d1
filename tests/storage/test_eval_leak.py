"""Replays of eval episodes (``storage.eval_split.replay_key``): the simulator is deterministic, so an eval
episode recorded again under a new id, or brought in from another data directory, is the same recording. The
catalog indexes no train episode that replays an eval episode, nor the reverse, and pins no eval episode a
train episode replays; ``Catalog.replays`` finds what a catalog made before these checks holds."""

from __future__ import annotations

import dataclasses
import uuid

import numpy as np
import pytest

import storage.eval_split
from storage import episodes
from storage.catalog import Catalog
from storage.errors import CatalogError
from storage.records import Episode
from tests.storage.test_episodes import make_episode


def replay(ep: Episode, steps: int | None = None, **meta) -> Episode:
    """``ep`` recorded again: a new id (and time, worker, ...), the same frames; ``steps`` keeps that many (or
    repeats its last step, for a longer recording: its first frames are ``ep``'s)."""
    n = len(ep) if steps is None else steps
    take = np.minimum(np.arange(n), len(ep) - 1)
    meta = dataclasses.replace(ep.meta, episode_id=uuid.uuid4().hex, created="2026-12-01T00:00:00+00:00",
                               worker_id="w9", request_id="r9", software_version="9.9", **meta)
    return Episode(meta, ep.frames[take], ep.actions[take], ep.states[take])


def files_and_rows(cat: Catalog) -> tuple[list[str], list[str]]:
    return (sorted(p.name for p in cat.episodes_dir.rglob("*") if p.is_file()),
            [r.episode_id for r in cat.list()])


def old_catalog_add(monkeypatch, cat: Catalog, ep: Episode, split: str = "train") -> None:
    """Index ``ep`` as a catalog made before the replay check would have."""
    with monkeypatch.context() as m:
        m.setattr(storage.eval_split, "refuse_replay", lambda conn, meta, split: None, raising=False)
        cat.add_episode(ep, split=split)


@pytest.mark.parametrize("pinned", [True, False])
def test_a_train_replay_of_an_eval_episode_is_refused_and_changes_nothing(cat, rng, tmp_path, pinned):
    ev = make_episode(rng)
    cat.add_episode(ev, split="eval")
    if pinned:
        cat.pin_eval_split([ev.meta.episode_id])
    before = files_and_rows(cat)
    for copy in (replay(ev), replay(ev, steps=len(ev) + 3), replay(ev, steps=2)):  # as long, longer, shorter
        with pytest.raises(CatalogError, match=rf"episode {copy.meta.episode_id} replays eval episode "
                                               rf"{ev.meta.episode_id} .*: training on it would leak the eval split"):
            cat.add_episode(copy)
        path = tmp_path / f"{copy.meta.episode_id}.mcap"  # from another data directory
        episodes.write_episode(path, copy)
        with pytest.raises(CatalogError, match=f"replays eval episode {ev.meta.episode_id}"):
            cat.ingest_file(path)
        assert files_and_rows(cat) == before and cat.snapshot().ids == []
    # the same start state, policy and physics with another seed is another recording; so is another policy
    other_seed = cat.add_episode(replay(ev, seed=ev.meta.seed + 1))
    other_policy = cat.add_episode(replay(ev, policy="random_waypoints"))
    assert cat.snapshot().ids == sorted([other_seed.episode_id, other_policy.episode_id])


def test_an_eval_episode_a_train_episode_already_records_is_refused(cat, rng):
    train = cat.add_episode(make_episode(rng))
    again = replay(cat.load(train.episode_id))
    with pytest.raises(CatalogError, match=rf"episode {again.meta.episode_id} replays train episode "
                                           rf"{train.episode_id} .*measured on their own training data"):
        cat.add_episode(again, split="eval")
    assert cat.count(split="eval") == 0
    assert not cat.add_episode(replay(again), split="train").duplicate  # train copies of train: no leak


def test_numbers_count_by_value(cat, rng):
    ev = make_episode(rng)
    ev.meta.physics = {**ev.meta.physics, "friction": 1.0}
    cat.add_episode(ev, split="eval")
    copy = replay(ev, physics={**ev.meta.physics, "friction": 1}, control_hz=10)
    with pytest.raises(CatalogError, match="replays eval episode"):
        cat.add_episode(copy)


def test_pin_refuses_an_eval_episode_a_train_episode_replays(cat, rng, monkeypatch):
    ev, kept = make_episode(rng), make_episode(rng)
    copy = replay(ev)
    old_catalog_add(monkeypatch, cat, copy)  # indexed before the catalog refused copies
    old_catalog_add(monkeypatch, cat, ev, split="eval")
    cat.add_episode(kept, split="eval")
    with pytest.raises(CatalogError, match=rf"eval episode {ev.meta.episode_id} is replayed by train episode "
                                           rf"{copy.meta.episode_id}: .*quarantine {copy.meta.episode_id}"):
        cat.pin_eval_split([ev.meta.episode_id, kept.meta.episode_id])
    assert cat.eval_split() is None
    assert cat.replays("train") == {copy.meta.episode_id: ev.meta.episode_id}
    assert cat.replays("eval") == {ev.meta.episode_id: copy.meta.episode_id}
    cat.quarantine(copy.meta.episode_id, "a copy of an eval episode")  # the way out: nothing trains on it
    digest = cat.pin_eval_split([ev.meta.episode_id, kept.meta.episode_id])
    assert cat.eval_split().hash == digest and cat.replays("train") == {}
