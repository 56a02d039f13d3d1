"""Catalog.repair_file, a worker's repeated upload of an episode's bytes: puts back a lost file, keeps the bytes of
a quarantined episode whose file is gone in quarantine/ (for a restore), and never ends a quarantine, not even one
that commits while it runs; a copy whose row does not commit is removed again."""

from __future__ import annotations

import pytest

from storage import files, quarantine
from storage.catalog import Catalog
from storage.database import connect
from storage.errors import CatalogError
from storage.quarantine import quarantine_path
from tests.storage.test_episodes import make_episode


def _stored(cat: Catalog, rng):
    row = cat.get(cat.add_episode(make_episode(rng)).episode_id)
    return row, row.path.read_bytes(), cat.data_dir / quarantine_path(row.path.relative_to(cat.data_dir).as_posix())


def _moved_to(cat: Catalog, episode_id: str) -> str:
    with connect(cat.db_path) as conn:
        return quarantine.find(conn, episode_id)["moved_to"]


def test_a_lost_file_is_put_back_and_an_intact_one_left_alone(cat, rng):
    row, data, kept = _stored(cat, rng)
    assert cat.repair_file(row.episode_id, data) is None  # intact: nothing written
    row.path.unlink()
    assert cat.repair_file(row.episode_id, data) == row.path
    assert row.path.read_bytes() == data and not kept.exists() and cat.get(row.episode_id).quarantined == ""


def test_the_bytes_of_a_quarantined_episode_whose_file_is_gone_are_kept_for_a_restore(cat, rng):
    row, data, kept = _stored(cat, rng)
    row.path.unlink()
    cat.quarantine(row.episode_id, "found by a training job: missing", only_if_damaged=True)
    assert _moved_to(cat, row.episode_id) == ""

    assert cat.repair_file(row.episode_id, data) == kept

    assert kept.read_bytes() == data and not row.path.exists()
    assert _moved_to(cat, row.episode_id) == kept.relative_to(cat.data_dir).as_posix()
    assert cat.get(row.episode_id).quarantined == "found by a training job: missing" and cat.snapshot().ids == []
    assert cat.repair_file(row.episode_id, data) is None  # an intact copy is kept now
    assert cat.restore(row.episode_id).quarantined == "" and files.holds(row.path, row.sha256)


def test_a_quarantine_that_commits_after_the_check_stands_and_the_bytes_go_to_quarantine(cat, rng, monkeypatch):
    """The file was lost; the repeat's bytes are staged beside it; then a training job's quarantine (another
    process) commits, with nothing to move. Under the write lock the bytes go to quarantine/, not back in place."""
    row, data, kept = _stored(cat, rng)
    row.path.unlink()
    real_stage = files.stage_bytes

    def stage_then_quarantine(path, payload):
        staged = real_stage(path, payload)
        Catalog(cat.data_dir).quarantine(row.episode_id, "found by a training job: missing", only_if_damaged=True)
        return staged
    monkeypatch.setattr("storage.catalog.stage_bytes", stage_then_quarantine)

    assert cat.repair_file(row.episode_id, data) == kept

    assert cat.get(row.episode_id).quarantined == "found by a training job: missing"
    assert kept.read_bytes() == data and [p for p in cat.episodes_dir.rglob("*") if p.is_file()] == []
    assert cat.restore(row.episode_id).quarantined == "" and row.path.read_bytes() == data


def test_a_kept_copy_whose_row_does_not_commit_is_removed(cat, rng, monkeypatch):
    row, data, kept = _stored(cat, rng)
    row.path.unlink()
    cat.quarantine(row.episode_id, "operator: lost", only_if_damaged=True)
    real_keep = quarantine.keep_copy

    def keep_then_break_the_commit(conn, *args):
        # A deferred foreign key is checked at COMMIT: this one makes the real COMMIT fail.
        conn.execute("PRAGMA defer_foreign_keys = ON")
        conn.execute("INSERT INTO eval_split_members(episode_id) VALUES ('no-such-episode')")
        real_keep(conn, *args)
    monkeypatch.setattr(quarantine, "keep_copy", keep_then_break_the_commit)

    with pytest.raises(CatalogError, match="FOREIGN KEY constraint failed"):
        cat.repair_file(row.episode_id, data)

    assert not kept.exists() and _moved_to(cat, row.episode_id) == ""
    assert [p for p in (cat.data_dir / "quarantine").rglob("*") if p.is_file()] == []  # no staging file either
    monkeypatch.undo()
    assert cat.repair_file(row.episode_id, data) == kept and cat.restore(row.episode_id).quarantined == ""


def test_other_bytes_are_refused_and_nothing_is_written(cat, rng):
    row, data, kept = _stored(cat, rng)
    row.path.unlink()
    with pytest.raises(CatalogError, match="refusing to repair it with other bytes"):
        cat.repair_file(row.episode_id, data[:-1])
    assert not row.path.exists() and not kept.exists()
