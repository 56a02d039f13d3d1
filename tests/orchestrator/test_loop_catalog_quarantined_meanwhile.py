"""`run` loads episodes by ids it read before (to plan a round, for the report): one an operator quarantines in
between (`episodes quarantine` moves its file aside) is left out, without being called damaged or a sign of an
unmounted disk, and without a warning that `run` quarantined it (as `uncertainty.data.load_train` does)."""

from __future__ import annotations

import logging

from orchestrator.loop_catalog import load_episodes
from storage.catalog import Catalog
from tests.uncertainty.synth import make_episode


def test_episodes_the_operator_quarantines_after_their_ids_were_read_are_left_out_quietly(tmp_path, caplog):
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(4))
    for episode_id in ids[1:]:  # the operator's bad batch, most of the split, after `run` read the ids
        Catalog(tmp_path).quarantine(episode_id, "operator: bad batch")
    caplog.set_level(logging.WARNING, logger="orchestrator.loop_catalog")
    loaded = load_episodes(cat, ids, "the report")
    assert [e.meta.episode_id for e in loaded] == ids[:1]
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert {Catalog(tmp_path).get(i).quarantined for i in ids[1:]} == {"operator: bad batch"}


def test_a_lost_file_is_still_quarantined_and_said(tmp_path, caplog):
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(4))
    cat.get(ids[0]).path.unlink()
    caplog.set_level(logging.WARNING, logger="orchestrator.loop_catalog")
    loaded = load_episodes(cat, ids, "the report")
    assert [e.meta.episode_id for e in loaded] == ids[1:]
    assert Catalog(tmp_path).get(ids[0]).quarantined.startswith("found by activecollect run")
    assert any("quarantined and left out of the report" in r.getMessage() for r in caplog.records)


def test_a_lost_file_the_operator_quarantines_first_is_not_said_to_be_ours(tmp_path, caplog, monkeypatch):
    """The operator's quarantine commits between `run`'s failed load and its own quarantine: the row keeps the
    operator's reason, and `run` neither claims it nor warns."""
    cat = Catalog(tmp_path)
    ids = sorted(cat.add_episode(make_episode(s, steps=5)).episode_id for s in range(4))
    cat.get(ids[0]).path.unlink()
    ours = cat.quarantine

    def operator_first(episode_id, reason, **kw):
        Catalog(tmp_path).quarantine(episode_id, "operator: wrong object")  # another process, committed first
        return ours(episode_id, reason, **kw)

    monkeypatch.setattr(cat, "quarantine", operator_first)
    caplog.set_level(logging.WARNING, logger="orchestrator.loop_catalog")
    loaded = load_episodes(cat, ids, "the report")
    assert [e.meta.episode_id for e in loaded] == ids[1:]
    assert Catalog(tmp_path).get(ids[0]).quarantined == "operator: wrong object"
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
