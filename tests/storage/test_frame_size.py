"""The catalog's one frame size: fixed by its first episode (a size a model trains on) or its pinned eval split;
an episode of another size is refused and changes nothing."""

from __future__ import annotations

import pytest

from storage import episodes
from storage.catalog import Catalog
from storage.errors import CatalogError
from tests.storage.test_catalog import all_files, mcap_files
from tests.storage.test_episodes import make_episode


def test_an_episode_of_another_frame_size_is_refused_and_changes_nothing(cat, rng, tmp_path):
    first = cat.add_episode(make_episode(rng, size=16))
    other = make_episode(rng, size=24)
    assert cat.frame_size() == 16
    with pytest.raises(CatalogError, match=rf"24px frames; this catalog holds 16px episodes \(its first episode, "
                                           rf"{first.episode_id}\)"):
        cat.add_episode(other)
    path = tmp_path / "other.mcap"
    path.write_bytes(episodes.encode_episode(other))
    with pytest.raises(CatalogError, match="24px frames"):
        cat.ingest_file(path)
    assert [r.episode_id for r in cat.list()] == [first.episode_id] and len(mcap_files(cat)) == 1
    assert not cat.add_episode(make_episode(rng, size=16)).duplicate  # the catalog's own size still goes in


@pytest.mark.parametrize("split", ["train", "eval"])
@pytest.mark.parametrize("size", [8, 12, 20])
def test_a_first_episode_at_a_size_no_model_trains_on_is_refused_and_changes_nothing(cat, rng, tmp_path, size,
                                                                                    split):
    """The first episode fixes every later one's size (``frame_size``): one no model trains on would make the
    whole catalog useless for training."""
    ep = make_episode(rng, size=size)
    data = episodes.encode_episode(ep)
    path = tmp_path / "first.mcap"
    path.write_bytes(data)
    words = (rf"episode {ep.meta.episode_id} has {size}px frames; the first episode fixes this catalog's frame "
             r"size, which must be a multiple of 8 from 16 to 1024 \(what a model trains on\)")
    for add in (lambda: cat.add_episode(ep, split=split), lambda: cat.ingest_bytes(data, split=split),
                lambda: cat.ingest_file(path, split=split)):
        with pytest.raises(CatalogError, match=words):
            add()
    assert cat.count() == 0 and cat.frame_size() is None and all_files(cat) == []
    assert not cat.add_episode(make_episode(rng, size=16), split=split).duplicate
    assert cat.frame_size() == 16


def test_a_catalog_fixed_at_an_untrainable_size_before_the_rule_keeps_taking_it(tmp_path, rng, monkeypatch):
    import storage.catalog
    cat = Catalog(tmp_path / "data")
    with monkeypatch.context() as m:  # a catalog from before the rule: its first episode is 12 px
        m.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)
        cat.add_episode(make_episode(rng, size=12))
    assert cat.frame_size() == 12
    assert not cat.add_episode(make_episode(rng, size=12)).duplicate  # its own size still goes in
    with pytest.raises(CatalogError, match=r"16px frames; this catalog holds 12px episodes \(its first episode"):
        cat.add_episode(make_episode(rng, size=16))
    assert cat.count() == 2


def test_a_pinned_eval_split_fixes_the_frame_size(tmp_path, rng, monkeypatch):
    import storage.catalog
    cat = Catalog(tmp_path / "data")
    assert cat.frame_size() is None
    with monkeypatch.context() as m:  # a catalog from before the rule: a 16 px episode first, then an 8 px split
        m.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)
        cat.add_episode(make_episode(rng, size=16))
        cat.pin_eval_split([cat.add_episode(make_episode(rng, size=8), split="eval").episode_id],
                           params={"image_size": 8})
    assert cat.frame_size() == 8  # what the models are evaluated on
    with pytest.raises(CatalogError, match=r"16px frames; this catalog holds 8px episodes \(its eval split\)"):
        cat.add_episode(make_episode(rng, size=16))
    cat.add_episode(make_episode(rng, size=8))


def test_pinning_refuses_params_that_misstate_the_frame_size_and_odd_sizes_are_refused(cat, rng):
    ep = cat.add_episode(make_episode(rng, size=16), split="eval").episode_id
    for said in (24, True, "16"):
        with pytest.raises(CatalogError, match=f"params say image_size {said!r}, the episodes have 16px"):
            cat.pin_eval_split([ep], params={"image_size": said})
    assert cat.eval_split() is None
    cat.pin_eval_split([ep], params={"image_size": 16})
    tiny = make_episode(rng, size=4)
    with pytest.raises(CatalogError, match="4px frames; expected 8..1024"):
        cat.add_episode(tiny)


def test_a_reader_that_asks_for_a_frame_size_refuses_another_from_the_metadata_before_inflating(rng):
    """What the service's upload path asks for: a file of another size is refused before a chunk is inflated, even
    one whose chunk would inflate past what its frames need."""
    from storage.episode_reader import read_episode
    from storage.errors import FrameSizeError
    from tests.storage.test_episodes import _episode_like_mcap
    other = make_episode(rng, size=24)
    assert read_episode(episodes.encode_episode(other), frame_size=24).meta.image_size == 24
    with pytest.raises(FrameSizeError, match=r"<bytes>: 24px frames, expected 16px") as info:
        read_episode(_episode_like_mcap(other, pad=32 << 20), frame_size=16)  # (else OversizedEpisodeError)
    assert (info.value.found, info.value.expected) == (24, 16)
