"""What a quarantine leaves in ``DATA/quarantine/`` once its episode is back in training (nothing), and what
``episodes ls --quarantined`` shows of it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from storage import episodes
from storage.catalog import Catalog
from tests.conftest import run_cli
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2121)


def _damaged_and_quarantined(cat: Catalog, rng: np.random.Generator) -> tuple[str, bytes]:
    """An episode whose file was damaged on disk and quarantined for it (as a retrain or `verify --quarantine`
    does); returns its id and its original bytes."""
    data = episodes.encode_episode(make_episode(rng))
    res = cat.ingest_bytes(data)
    res.path.write_bytes(data[:200] + bytes([data[200] ^ 1]) + data[201:])
    assert cat.quarantine(res.episode_id, "damaged on disk", only_if_damaged=True).quarantined
    return res.episode_id, data


def _quarantine_files(cat: Catalog) -> list:
    return sorted((cat.data_dir / "quarantine").rglob("*.mcap"))


def test_ingesting_the_original_bytes_leaves_no_damaged_file_behind(tmp_path, rng):
    """The damaged file a quarantine took aside stayed in quarantine/ once the original bytes were ingested again:
    no row named it any more, so nothing showed it and nothing ever deleted it."""
    cat = Catalog(tmp_path / "data")
    episode_id, data = _damaged_and_quarantined(cat, rng)
    assert len(_quarantine_files(cat)) == 1

    res = cat.ingest_bytes(data)

    assert res.restored and not cat.get(episode_id).quarantined
    cat.verify(episode_id)
    assert _quarantine_files(cat) == []


def test_a_restore_whose_bytes_are_already_in_place_leaves_no_damaged_file_behind(tmp_path, rng):
    """An ingest of the original bytes killed after putting them in place, before its commit: the episode is still
    quarantined, its damaged file still aside. Restoring it leaves nothing aside."""
    cat = Catalog(tmp_path / "data")
    episode_id, data = _damaged_and_quarantined(cat, rng)
    cat.get(episode_id).path.write_bytes(data)

    assert not cat.restore(episode_id).quarantined

    cat.verify(episode_id)
    assert _quarantine_files(cat) == []


def test_an_intact_copy_still_comes_back_with_restore(tmp_path, rng):
    """(Unchanged) an episode an operator quarantined comes back from its copy in quarantine/."""
    cat = Catalog(tmp_path / "data")
    res = cat.ingest_bytes(episodes.encode_episode(make_episode(rng)))
    cat.quarantine(res.episode_id, "looks wrong")
    assert not res.path.exists() and len(_quarantine_files(cat)) == 1

    assert not cat.restore(res.episode_id).quarantined

    cat.verify(res.episode_id)
    assert _quarantine_files(cat) == []


def test_episodes_ls_quarantined_shows_where_each_file_is_kept_and_the_space_they_take(tmp_path, rng, capsys):
    data = tmp_path / "data"
    cat = Catalog(data)
    kept_id = cat.ingest_bytes(episodes.encode_episode(make_episode(rng))).episode_id
    gone = cat.ingest_bytes(episodes.encode_episode(make_episode(rng)))
    cat.ingest_bytes(episodes.encode_episode(make_episode(rng)))
    cat.quarantine(kept_id, "operator: wrong object")
    gone.path.unlink()
    cat.quarantine(gone.episode_id, "file lost")
    kept = data / "quarantine" / cat.get(kept_id).path.parent.name / f"{kept_id}.mcap"
    size = kept.stat().st_size

    rc, out, _ = run_cli(capsys, "episodes", "ls", "--quarantined", "--data", str(data))

    assert rc == 0
    assert f"  kept: {kept} ({size / 1e3:.0f}KB)" in out
    assert "  kept: no file (only an ingest of its original bytes brings it back)" in out
    assert (f"2 of 3 episodes (2 quarantined); the files of those shown take {size / 1e6:.1f} MB in "
            f"{data / 'quarantine'}") in out
    rc, out, _ = run_cli(capsys, "episodes", "ls", "--quarantined", "--data", str(data), "--json")
    by_id = {r["episode_id"]: r for r in json.loads(out)}
    assert by_id[kept_id]["kept"] == str(kept) and by_id[kept_id]["kept_bytes"] == size
    assert by_id[gone.episode_id]["kept"] is None and by_id[gone.episode_id]["kept_bytes"] == 0
    rc, out, _ = run_cli(capsys, "episodes", "ls", "--data", str(data), "--json")
    assert all("kept" not in r for r in json.loads(out) if not r["quarantined"])
