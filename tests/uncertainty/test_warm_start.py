"""Warm starts (``--from-champion``): from a damaged champion, a read that fails for now, settings overridden."""

from __future__ import annotations

import logging
import pathlib

import pytest

from orchestrator.retrain import run_retrain
from storage.catalog import Catalog
from storage.errors import RegistryUnavailableError
from storage.models import ModelRegistry, ModelStatus
from tests.conftest import failing_reads_of
from tests.uncertainty.conftest import TINY
from tests.uncertainty.synth import make_episode
from uncertainty.checkpoint import save_candidate
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig
from uncertainty.train import TrainConfig, train_candidate

WARM = TrainConfig(epochs=1, from_champion=True, **TINY)


def _catalog(tmp_path: pathlib.Path) -> Catalog:
    cat = Catalog(tmp_path)
    for s in range(3):
        cat.add_episode(make_episode(s, "T", steps=8))
    cat.pin_eval_split([cat.add_episode(make_episode(50, "T", steps=8), split="eval").episode_id])
    return cat


def _champion(cat: Catalog, registry: ModelRegistry, seed: int, variance_head: bool = False) -> str:
    """An untrained model of TINY's shape, registered on the catalog's eval split and made champion."""
    config = PredictorConfig(image_size=16, context=2, widths=TINY["widths"], predict_variance=variance_head)
    ens = Ensemble(config, members=TINY["members"], seed=seed)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    version = save_candidate(registry, ens, {"h1_mse": 0.01}, cat.snapshot().snapshot_id, cat.eval_split().hash)
    assert registry.promote(version).promoted
    return version


def _flip_a_byte(registry: ModelRegistry, version: str) -> None:
    weights = registry.get(version).weights_path
    data = bytearray(weights.read_bytes())
    data[-100] ^= 0xFF
    weights.write_bytes(bytes(data))


def test_a_damaged_champion_is_replaced_by_a_warm_start_from_the_newest_sound_earlier_champion(tmp_path, caplog):
    cat, registry = _catalog(tmp_path), ModelRegistry(tmp_path)
    sound = _champion(cat, registry, 0)
    damaged_too = _champion(cat, registry, 1)
    champion = _champion(cat, registry, 2)
    _flip_a_byte(registry, damaged_too)
    _flip_a_byte(registry, champion)

    with caplog.at_level(logging.WARNING, logger="uncertainty.train"):
        result = train_candidate(cat, registry, WARM)
    assert result.decision.promoted and registry.champion() == result.version
    assert f"replaces champion {champion}, whose weights are unusable" in result.decision.reason
    assert registry.get(champion).status == ModelStatus.RETIRED
    rec = registry.get(result.version)
    assert rec.parent == sound
    assert rec.config["train"]["warm_start_from"] == sound == result.metrics["warm_start_from"]
    note = result.metrics["warm_start_note"]
    assert note.startswith(f"champion {champion} cannot be loaded (checkpoint {champion}: weights sha256 mismatch")
    assert note.endswith(f"warm-started from {sound}, the newest sound model of its rollback chain")
    assert rec.config["train"]["warm_start_note"] == note and result.warnings == [note]
    assert [r.getMessage() for r in caplog.records] == [note]


@pytest.mark.parametrize("damage", ["flipped byte", "missing file"])
def test_a_retrain_from_a_damaged_champion_with_nothing_sound_before_it_trains_a_fresh_model(tmp_path, damage):
    cat, registry = _catalog(tmp_path), ModelRegistry(tmp_path)
    champion = _champion(cat, registry, 0)
    if damage == "flipped byte":
        _flip_a_byte(registry, champion)
    else:
        registry.get(champion).weights_path.unlink()
    cfg = TrainConfig(epochs=1, from_champion=True, **dict(TINY, members=3))

    result = run_retrain(tmp_path, cfg)
    assert result["promoted"] and result["champion"] == result["version"] == registry.champion()
    assert "whose weights are unusable" in result["reason"]
    rec = registry.get(result["version"])
    assert rec.parent is None and rec.config["members"] == 3  # a fresh model of the shape asked for
    assert rec.config["train"]["warm_start_from"] is None and result["metrics"]["warm_start_from"] is None
    note = rec.metrics["warm_start_note"]
    assert note.startswith(f"champion {champion} cannot be loaded") and note.endswith("trained a fresh model")
    assert result["warnings"] == [note] and result["metrics"]["warm_start_note"] == note


def test_a_read_error_on_the_model_to_warm_start_from_fails_the_retrain_for_now(tmp_path, monkeypatch):
    cat, registry = _catalog(tmp_path), ModelRegistry(tmp_path)
    earlier = _champion(cat, registry, 0)
    champion = _champion(cat, registry, 1)
    before = [(m.version, m.status) for m in registry.list()]
    with monkeypatch.context() as m:
        failing_reads_of(registry.get(champion).weights_path, m)
        with pytest.raises(RegistryUnavailableError, match=f"cannot warm-start from {champion} now: .*Input/output"):
            run_retrain(tmp_path, WARM)
    assert [(m.version, m.status) for m in registry.list()] == before and registry.champion() == champion
    # the same for the earlier champion a damaged one would be replaced from: not skipped for a passing error
    _flip_a_byte(registry, champion)
    with monkeypatch.context() as m:
        failing_reads_of(registry.get(earlier).weights_path, m)
        with pytest.raises(RegistryUnavailableError, match=f"cannot warm-start from {earlier} now"):
            run_retrain(tmp_path, WARM)
    assert [(m.version, m.status) for m in registry.list()] == before and registry.champion() == champion
    # once the disk reads again, the job goes on: from the earlier champion, the damaged one replaced
    result = run_retrain(tmp_path, WARM)
    assert result["promoted"] and registry.get(result["version"]).parent == earlier


def test_a_warm_start_warns_of_the_settings_it_overrode(tmp_path, caplog):
    cat, registry = _catalog(tmp_path), ModelRegistry(tmp_path)
    champion = _champion(cat, registry, 0, variance_head=True)
    asked = TrainConfig(epochs=1, from_champion=True, context=3, **dict(TINY, members=3))
    with caplog.at_level(logging.WARNING, logger="uncertainty.train"):
        result = train_candidate(cat, registry, asked)
    overrode = "members 3 (kept 2); context 3 (kept 2); variance_head False (kept True)"
    assert result.metrics["warm_start_overrode"] == overrode
    assert registry.get(result.version).config["train"]["warm_start_overrode"] == overrode
    assert result.metrics["warm_start_from"] == champion and "warm_start_note" not in result.metrics
    line = f"warm start from {champion} keeps its shape, not the one asked for: {overrode}"
    assert result.warnings == [line] and [r.getMessage() for r in caplog.records] == [line]
    # asked for the champion's own shape: nothing to say
    same = train_candidate(cat, registry, TrainConfig(epochs=1, from_champion=True, variance_head=True, **TINY))
    assert same.warnings == [] and "warm_start_overrode" not in same.metrics
