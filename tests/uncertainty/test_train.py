import numpy as np
import pytest
import torch

import uncertainty.train
from storage.catalog import Catalog
from storage.errors import RegistryUnavailableError
from storage.models import ModelRegistry, ModelStatus
from tests.conftest import failing_reads_of
from tests.uncertainty.conftest import TINY, baseline_mse
from tests.uncertainty.synth import make_episode
from uncertainty.checkpoint import load_ensemble
from uncertainty.data import load_train
from uncertainty.errors import ConfigError, DataError
from uncertainty.train import (TrainConfig, evaluate, evaluate_episodes, fit, new_ensemble, train_candidate,
                               train_windows, variance_loss)


def test_tiny_model_overfits_a_tiny_dataset(trained, t_episodes):
    ens, losses = trained
    assert losses[-1] < losses[0] / 5
    assert losses[-1] < baseline_mse(t_episodes) / 5


def test_same_seed_same_training():
    eps = [make_episode(s, steps=6) for s in range(2)]
    cfg = TrainConfig(epochs=1, seed=3, bootstrap=True, **TINY)
    a, b = new_ensemble(cfg, eps), new_ensemble(cfg, eps)
    la, lb = fit(a, train_windows(eps, a, cfg), cfg), fit(b, train_windows(eps, b, cfg), cfg)
    assert la == lb
    assert all(np.array_equal(x.detach().numpy(), y.detach().numpy()) for x, y in zip(a.params, b.params))


def test_a_batch_larger_than_the_data_trains_on_the_data_once_per_step():
    """A batch past a member's windows only repeated them, allocating the batch: --batch-size 10**12 on a few
    windows was a MemoryError traceback."""
    eps = [make_episode(s, steps=6) for s in range(2)]
    huge, fits = (TrainConfig(epochs=1, seed=3, **{**TINY, "batch_size": b}) for b in (10**12, 10**3))
    a, b = new_ensemble(huge, eps), new_ensemble(fits, eps)
    assert fit(a, train_windows(eps, a, huge), huge) == fit(b, train_windows(eps, b, fits), fits)


def test_disagreement_is_higher_out_of_distribution(trained):
    ens, _ = trained
    held_out = [make_episode(seed, "T", steps=12) for seed in range(100, 104)]
    novel = [make_episode(seed, shape, steps=12) for seed in range(100, 102) for shape in ("disk", "L")]

    def mean_dis(eps):
        return float(np.mean([np.nanmean(ens.disagreement(e.frames, e.actions)) for e in eps]))

    assert mean_dis(novel) > 1.5 * mean_dis(held_out)


def test_evaluate_reports_accuracy_next_to_baseline_and_calibration(trained):
    ens, _ = trained
    eps = [make_episode(seed, "T", steps=12) for seed in range(200, 203)]
    m = evaluate_episodes(ens, eps, "hash", horizons=(1, 5, 10), rollout_stride=2)
    for h in (1, 5, 10):
        assert {f"h{h}_mse", f"h{h}_psnr", f"h{h}_ssim", f"baseline_h{h}_mse"} <= m.keys()
    assert m["h1_mse"] < m["baseline_h1_mse"]
    assert m["h1_psnr"] > m["baseline_h1_psnr"]
    assert -1 <= m["spearman"] <= 1
    assert len(m["sparsification"]["curve"]) == 10
    assert m["eval_split_hash"] == "hash" and m["eval_windows"] == 3 * 10


def test_variance_loss_is_minimised_by_the_true_error_variance():
    """Minimising variance_loss over a free log-variance finds the squared error's mean, pixel by pixel."""
    g = torch.Generator().manual_seed(0)
    scale = torch.tensor([0.003, 0.03, 0.3]).reshape(1, 1, 3, 1, 1)                  # three noise levels
    target = torch.randn(1, 4096, 3, 2, 2, generator=g) * scale                         # (K, B, 3, H, W)
    mean = torch.zeros_like(target)
    logvar = torch.full((1, 1, 3, 2, 2), -7.0, requires_grad=True)
    opt = torch.optim.Adam([logvar], lr=0.05)
    for _ in range(1500):
        opt.zero_grad()
        variance_loss(mean, logvar.expand_as(target), target).sum().backward()
        opt.step()
    found = logvar.detach().exp().sqrt().reshape(3, 4).mean(dim=1)
    torch.testing.assert_close(found, scale.flatten(), rtol=0.1, atol=0)


def test_variance_loss_leaves_the_mean_to_the_squared_error():
    target = torch.rand(2, 3, 3, 4, 4)
    mean = torch.zeros_like(target, requires_grad=True)
    logvar = torch.zeros_like(target, requires_grad=True)
    variance_loss(mean, logvar, target).sum().backward()
    assert logvar.grad.abs().sum() > 0
    assert mean.grad is None


def test_variance_head_learns_where_the_error_is_and_reports_total_calibration(t_episodes):
    """Trained with a variance head: the frames are as good, the predicted variance ranks the error."""
    cfg = TrainConfig(epochs=60, seed=0, variance_head=True, **TINY)
    ens = new_ensemble(cfg, t_episodes)
    losses = fit(ens, train_windows(t_episodes, ens, cfg), cfg)
    assert losses[-1] < baseline_mse(t_episodes) / 5
    eps = [make_episode(seed, "T", steps=12) for seed in range(200, 203)]
    m = evaluate_episodes(ens, eps, "hash", horizons=(1,))
    assert m["h1_mse"] < m["baseline_h1_mse"]
    assert m["spearman_predicted_variance"] > 0.5 and m["h1_predicted_variance"] > 0
    assert m["spearman_total"] > m["spearman"]
    assert 0.1 < m["h1_total_variance_ratio"] < 10
    assert len(m["sparsification_total"]["curve"]) == 10


def test_a_variance_head_survives_the_registry_and_gates_like_any_model(tmp_path):
    cat, eval_ids = _catalog(tmp_path)
    cat.pin_eval_split(eval_ids)
    registry = ModelRegistry(tmp_path)
    result = train_candidate(cat, registry, TrainConfig(epochs=2, variance_head=True, eval_rollout_stride=3, **TINY))
    assert result.decision.promoted and "spearman_total" in result.metrics
    loaded = load_ensemble(registry, result.version, "cpu")
    assert loaded.config.predict_variance
    again = evaluate(loaded, cat)
    assert again["spearman_total"] == pytest.approx(result.metrics["spearman_total"])
    # warm starts keep the head; asking a head-less champion for one is refused
    warm = train_candidate(cat, registry, TrainConfig(epochs=1, from_champion=True, **TINY))
    assert load_ensemble(registry, warm.version, "cpu").config.predict_variance
    assert again["h1_predicted_variance"] == pytest.approx(result.metrics["h1_predicted_variance"], rel=1e-5)


def _catalog(tmp_path, n_train=4, n_eval=2):
    cat = Catalog(tmp_path)
    for s in range(n_train):
        cat.add_episode(make_episode(s, "T", steps=8))
    ids = [cat.add_episode(make_episode(50 + s, "T", steps=8), split="eval").episode_id for s in range(n_eval)]
    return cat, ids


def test_train_candidate_trains_on_train_split_evaluates_on_eval_split_and_gates(tmp_path):
    cat, eval_ids = _catalog(tmp_path)
    cat.pin_eval_split(eval_ids)
    registry = ModelRegistry(tmp_path)
    result = train_candidate(cat, registry, TrainConfig(epochs=2, eval_rollout_stride=3, **TINY))
    assert result.decision.promoted and registry.champion() == result.version
    rec = registry.get(result.version)
    assert rec.eval_split_hash == cat.eval_split().hash == result.metrics["eval_split_hash"]
    assert rec.snapshot_id == cat.snapshot().snapshot_id
    assert result.metrics["train_episodes"] == 4 and result.metrics["eval_episodes"] == 2
    # the train data never includes an eval episode, the evaluation only eval episodes
    train = load_train(cat)
    assert not set(train.episode_ids) & set(eval_ids)
    assert result.metrics["eval_windows"] == 2 * 6
    # warm start from the champion; it is registered with the champion as parent
    warm = train_candidate(cat, registry, TrainConfig(epochs=1, from_champion=True, **TINY))
    assert registry.get(warm.version).parent == result.version
    assert registry.get(warm.version).status in (ModelStatus.CHAMPION, ModelStatus.REJECTED)
    again = evaluate(load_ensemble(registry, result.version, "cpu"), cat)
    assert again["h1_mse"] == pytest.approx(result.metrics["h1_mse"], rel=1e-5)


def test_train_candidate_needs_an_eval_split(tmp_path):
    cat, _ = _catalog(tmp_path, n_eval=1)
    with pytest.raises(DataError, match="no eval split"):
        train_candidate(cat, ModelRegistry(tmp_path), TrainConfig(epochs=1, **TINY))


def test_warm_start_without_champion_is_refused(tmp_path):
    cat, ids = _catalog(tmp_path, n_train=1, n_eval=1)
    cat.pin_eval_split(ids)
    with pytest.raises(ConfigError, match="no champion"):
        train_candidate(cat, ModelRegistry(tmp_path), TrainConfig(epochs=1, from_champion=True, **TINY))
    registry = ModelRegistry(tmp_path)
    train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    with pytest.raises(ConfigError, match="no variance head"):
        train_candidate(cat, registry, TrainConfig(epochs=1, from_champion=True, variance_head=True, **TINY))


def test_a_refused_warm_start_leaves_a_damaged_train_episode_where_it_is(tmp_path):
    """Reading the train snapshot quarantines a damaged episode (moves its file): a job whose warm start is refused
    (no champion, no variance head) must not get that far."""
    cat, ids = _catalog(tmp_path, n_train=4, n_eval=1)
    cat.pin_eval_split(ids)
    registry = ModelRegistry(tmp_path)
    damaged = cat.list(split="train")[0]
    for cfg in (TrainConfig(epochs=1, from_champion=True, **TINY),
                TrainConfig(epochs=1, from_champion=True, variance_head=True, **TINY)):
        with pytest.raises(ConfigError, match="no champion|no variance head"):
            train_candidate(cat, registry, cfg)
        if registry.champion() is None:
            train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))  # (then damaged: this one reads it)
            damaged.path.write_bytes(damaged.path.read_bytes()[:-3])
        assert cat.count(quarantined=True) == 0 and damaged.path.exists()
    assert train_candidate(cat, registry, TrainConfig(epochs=1, **TINY)).quarantined == [damaged.episode_id]


def test_a_champion_the_gate_cannot_read_now_stops_the_job_before_it_trains(tmp_path, monkeypatch):
    cat, ids = _catalog(tmp_path, n_train=4, n_eval=1)
    cat.pin_eval_split(ids)
    registry = ModelRegistry(tmp_path)
    champion = train_candidate(cat, registry, TrainConfig(epochs=1, **TINY)).version
    failed = failing_reads_of(registry.get(champion).weights_path, monkeypatch)
    with pytest.raises(RegistryUnavailableError, match=f"cannot read champion {champion}, which the gate compares"):
        train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    assert failed and [m.version for m in registry.list()] == [champion]  # nothing trained, nothing registered


def test_a_gate_that_cannot_read_the_champion_now_names_the_candidate_it_leaves(tmp_path, monkeypatch):
    """The read fails between the job's start and its gate: the candidate is registered, and the error says so
    (the gate's own "nothing changed" is not the job's)."""
    cat, ids = _catalog(tmp_path, n_train=4, n_eval=1)
    cat.pin_eval_split(ids)
    registry = ModelRegistry(tmp_path)
    champion = train_candidate(cat, registry, TrainConfig(epochs=1, **TINY)).version
    real_fit = uncertainty.train.fit

    def fit_then_lose_the_disk(*args, **kw):
        failing_reads_of(registry.get(champion).weights_path, monkeypatch, times=10)
        return real_fit(*args, **kw)
    monkeypatch.setattr(uncertainty.train, "fit", fit_then_lose_the_disk)
    with pytest.raises(RegistryUnavailableError) as info:
        train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    left = [m.version for m in registry.list() if m.version != champion]
    assert len(left) == 1 and registry.get(left[0]).status is ModelStatus.CANDIDATE
    assert str(info.value).startswith(f"registered {left[0]} but cannot gate it now: ")
    assert str(info.value).endswith(f"the next training job rejects {left[0]} as abandoned")
    assert registry.champion() == champion


def test_a_model_the_eval_split_cannot_evaluate_is_refused_before_training(tmp_path, monkeypatch):
    import storage.catalog
    monkeypatch.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)  # a catalog from before it
    cat = Catalog(tmp_path)
    cat.add_episode(make_episode(0, "T", steps=8, size=16))
    cat.pin_eval_split([cat.add_episode(make_episode(50, "T", steps=8, size=32), split="eval").episode_id])
    registry = ModelRegistry(tmp_path)
    cfg = TrainConfig(epochs=1, **TINY)
    with pytest.raises(DataError, match="no train episode has the eval split's 32px frames: 1 of another size"):
        train_candidate(cat, registry, cfg)
    assert registry.list() == []  # refused before any training or registration


def test_a_warm_start_records_the_shape_it_trained_not_the_one_asked_for(tmp_path):
    cat, ids = _catalog(tmp_path, n_train=2, n_eval=1)
    cat.pin_eval_split(ids)
    registry = ModelRegistry(tmp_path)
    train_candidate(cat, registry, TrainConfig(epochs=1, **TINY))
    asked = dict(TINY, members=3)
    result = train_candidate(cat, registry, TrainConfig(epochs=1, from_champion=True, context=3, **asked))
    recorded = registry.get(result.version).config["train"]
    assert recorded["members"] == 2 and recorded["context"] == 2 and recorded["from_champion"]


@pytest.mark.parametrize("kwargs", [{"epochs": 0}, {"lr": -1.0}, {"device": "tpu"}, {"max_windows": 0},
                                    {"members": 65}, {"widths": (16, 32, 1025)}, {"widths": (0, 8, 8)},
                                    {"widths": (8, 8)}])
def test_train_config_refuses_bad_values(kwargs):
    with pytest.raises(ConfigError):
        TrainConfig(**kwargs)


def test_an_ensemble_of_one_is_refused_it_cannot_disagree():
    with pytest.raises(ConfigError, match="members must be >= 2 \\(one member cannot disagree\\), found 1"):
        TrainConfig(members=1)
