import numpy as np
import pytest
import torch

from tests.uncertainty.synth import make_episode
from uncertainty.train import TrainConfig, fit, new_ensemble, train_windows

# The machine's two cores are shared: one thread per test process degrades gracefully under load.
torch.set_num_threads(1)

TINY = dict(members=2, widths=(16, 16, 32), batch_size=8, lr=3e-3, device="cpu", progress=False)


@pytest.fixture(scope="session")
def t_episodes():
    """Training episodes of the toy "T" world (16x16)."""
    return [make_episode(seed, "T", steps=12) for seed in range(8)]


@pytest.fixture(scope="session")
def trained(t_episodes):
    """A 2-member ensemble trained on the toy "T" episodes for a few seconds."""
    cfg = TrainConfig(epochs=30, seed=0, **TINY)
    ens = new_ensemble(cfg, t_episodes)
    losses = fit(ens, train_windows(t_episodes, ens, cfg), cfg)
    return ens, losses


def baseline_mse(episodes) -> float:
    """Copy-last-frame MSE over all next-frame pairs, in [0, 1] pixel units."""
    errs = [np.mean((ep.frames[2:].astype(float) - ep.frames[1:-1]) ** 2) / 255 ** 2 for ep in episodes]
    return float(np.mean(errs))
