"""Edge cases of training and evaluation: a diverging run, an eval split too short or of another size, and an
old catalog whose train episodes have more than one frame size."""

import math

import pytest
import torch

import storage.catalog
from storage.catalog import Catalog
from storage.models import ModelRegistry
from tests.uncertainty.conftest import TINY
from tests.uncertainty.synth import make_episode
from uncertainty.checkpoint import save_candidate
from uncertainty.errors import DataError, DivergedError
from uncertainty.train import (TrainConfig, evaluate, evaluate_episodes, fit, new_ensemble, train_candidate,
                               train_windows)


def _catalog(tmp_path, train_steps=(8, 8), eval_steps=(8,), size: int = 16) -> Catalog:
    cat = Catalog(tmp_path)
    for seed, steps in enumerate(train_steps):
        cat.add_episode(make_episode(seed, "T", steps=steps, size=size))
    cat.pin_eval_split([cat.add_episode(make_episode(50 + seed, "T", steps=steps, size=size), split="eval").episode_id
                        for seed, steps in enumerate(eval_steps)])
    return cat


def test_a_diverging_fit_stops_at_the_first_non_finite_loss_with_its_weights_still_finite():
    eps = [make_episode(s, steps=6) for s in range(2)]
    cfg = TrainConfig(epochs=3, seed=0, **{**TINY, "lr": 1e9, "grad_clip": None})
    ens = new_ensemble(cfg, eps)
    with pytest.raises(DivergedError, match=r"training diverged: the loss is (nan|inf) at epoch \d of 3, step 1 of "
                                            r"\d+ \(learning rate 1e\+09\); train again with a lower learning rate"):
        fit(ens, train_windows(eps, ens, cfg), cfg)
    assert all(bool(torch.isfinite(p).all()) for p in ens.params)  # stopped before NaN reached the weights


def test_a_diverging_retrain_registers_no_candidate(tmp_path):
    cat = _catalog(tmp_path)
    registry = ModelRegistry(tmp_path)
    with pytest.raises(DivergedError, match="training diverged"):
        train_candidate(cat, registry, TrainConfig(epochs=3, **{**TINY, "lr": 1e9, "grad_clip": None}))
    assert registry.list() == [] and registry.champion() is None


@pytest.mark.parametrize("frames", [1, 2])
def test_an_eval_split_too_short_to_evaluate_is_refused_before_training(tmp_path, frames):
    cat = _catalog(tmp_path, eval_steps=(frames, frames))
    registry = ModelRegistry(tmp_path)
    with pytest.raises(DataError, match=f"the eval split's episodes are too short to evaluate a model of context 2: "
                                        f"the longest has {frames} frame\\(s\\), it needs 3"):
        train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert registry.list() == []


def test_an_eval_split_just_long_enough_is_evaluated_with_nan_only_at_the_horizons_it_cannot_reach(tmp_path):
    cat = _catalog(tmp_path, eval_steps=(3, 3))
    registry = ModelRegistry(tmp_path)
    result = train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert result.metrics["eval_windows"] == 2 and result.decision.promoted  # h1 finite: the gate takes it
    assert all(math.isnan(result.metrics[f"h{h}_mse"]) for h in (5, 10))  # no rollout fits in 3 frames


def test_evaluate_says_when_the_model_has_another_frame_size_than_the_eval_split(tmp_path):
    cat = _catalog(tmp_path, size=32)
    eps = [make_episode(s, steps=6) for s in range(2)]  # 16px
    ens = new_ensemble(TrainConfig(epochs=1, **TINY), eps)
    with pytest.raises(DataError, match="the eval split has 32px frames, the model 16px") as info:
        evaluate(ens, cat)
    assert "pin a new" not in str(info.value) and "a data directory of its own" in str(info.value)  # (never replaced)


def _old_catalog(tmp_path, monkeypatch, train_sizes) -> tuple[Catalog, list[str]]:
    """A catalog from before it held one frame size: 32px eval episodes, train episodes of ``train_sizes``."""
    monkeypatch.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)
    cat = Catalog(tmp_path)
    ids = [cat.add_episode(make_episode(seed, "T", steps=6, size=size)).episode_id
           for seed, size in enumerate(train_sizes)]
    cat.pin_eval_split([cat.add_episode(make_episode(50, "T", steps=6, size=32), split="eval").episode_id])
    return cat, ids


def test_a_retrain_on_an_old_catalog_of_two_frame_sizes_trains_on_the_eval_splits_and_says_so(tmp_path, monkeypatch,
                                                                                                caplog):
    cat, ids = _old_catalog(tmp_path, monkeypatch, train_sizes=(16, 32, 32))
    registry = ModelRegistry(tmp_path)
    with caplog.at_level("WARNING", logger="uncertainty.data"):
        result = train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert result.metrics["train_episodes"] == 2 and result.metrics["train_other_size_left_out"] == 1
    assert registry.snapshot(result.version).ids == sorted(ids[1:])  # what it was trained on
    assert registry.get(result.version).config["predictor"]["image_size"] == 32
    assert any(f"left out 1 train episode(s) whose frames are not the eval split's 32px: {ids[0]} (16px)" in line
               for line in result.warnings)
    assert "quarantine" in caplog.text


def test_an_old_catalog_with_no_train_episode_of_the_eval_splits_size_is_refused_in_one_line(tmp_path, monkeypatch):
    cat, ids = _old_catalog(tmp_path, monkeypatch, train_sizes=(16, 16))
    registry = ModelRegistry(tmp_path)
    with pytest.raises(DataError, match=f"no train episode has the eval split's 32px frames: 2 of another size "
                                        f"\\(first {min(ids)} at 16px, indexed before"):
        train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert registry.list() == []


def test_a_variance_head_model_without_error_on_the_eval_split_is_not_refused_as_non_finite(tmp_path):
    """White frames and members whose every predicted change is positive: clamped to 1, the mean is exact
    (h1_mse 0), and the variance-to-error ratio, undefined, must not read as a non-finite h1 metric to the gate."""
    eps = [make_episode(s, steps=6) for s in range(2)]
    for ep in eps:
        ep.frames[:] = 255
    ens = new_ensemble(TrainConfig(epochs=1, variance_head=True, **TINY), eps)
    with torch.no_grad():
        ens.params[ens.names.index("out.bias")].fill_(10.0)  # every member predicts brighter than white
    metrics = evaluate_episodes(ens, eps, "split-h")
    assert metrics["h1_mse"] == 0.0 and metrics["h1_total_variance_ratio"] is None
    registry = ModelRegistry(tmp_path)
    version = save_candidate(registry, ens, metrics, "snap", "split-h")
    decision = registry.gate(version, eval_split_hash="split-h")
    assert decision.promoted, decision.reason


def test_a_horizon_the_eval_episodes_are_too_short_for_leaves_the_shorter_ones_measured(trained):
    """8 frames: room for 5 steps after the 2 context frames, not 10. h5 is measured, only h10 is NaN."""
    ens, _ = trained
    eps = [make_episode(seed, "T", steps=8) for seed in range(200, 203)]
    m = evaluate_episodes(ens, eps, "hash", horizons=(1, 5, 10), rollout_stride=1)
    assert all(math.isfinite(m[f"h5_{k}"]) for k in ("mse", "psnr", "ssim", "disagreement"))
    assert m["h5_windows"] == 3 * 2 and m["h5_mse"] > m["h1_mse"]  # starts 1 and 2 of each episode
    assert all(math.isnan(m[f"h10_{k}"]) for k in ("mse", "psnr", "ssim"))


def test_a_horizon_is_measured_on_every_eval_episode_long_enough_for_it(trained):
    """Three episodes reach h5 only, one reaches h10 too (an eval split ingested and pinned by hand): h5 came from
    the h10 rollout alone, one window of the one long episode."""
    ens, _ = trained
    short, long = [make_episode(seed, "T", steps=8) for seed in range(200, 203)], make_episode(203, "T", steps=12)
    both = evaluate_episodes(ens, [*short, long], "hash", horizons=(1, 5, 10), rollout_stride=1)
    alone = {h: evaluate_episodes(ens, eps, "hash", horizons=(1, h), rollout_stride=1)
             for h, eps in ((5, [*short, long]), (10, [long]))}
    assert both["h5_windows"] == 3 * 2 + 6 and both["h10_windows"] == 1  # (starts 1..6 of the long one at h5)
    assert all(both[f"h{h}_{k}"] == alone[h][f"h{h}_{k}"] for h in (5, 10) for k in ("mse", "ssim", "disagreement"))
