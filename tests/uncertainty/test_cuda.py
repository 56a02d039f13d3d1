"""The model on CUDA (skipped where there is none: CI has no GPU; ``bench/device_checks.sh`` runs these on a GPU).

The fused pass must equal the members one by one there too (the issue's 1e-5, at the service's 64 px and at a
batch the service scores; its gradients: ``test_ensemble.py``, on either device); a model trained on the GPU must
load and predict on a machine without one (checkpoints are read with ``map_location="cpu"``), and the two devices
must agree on its scores within float32 rounding (TF32 convolutions are off: ``uncertainty.model``).
"""

import numpy as np
import pytest
import torch

from tests.uncertainty.synth import make_episode
from tests.uncertainty.test_ensemble import _noisy
from uncertainty.checkpoint import ensemble_from_bytes, ensemble_to_bytes
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig
from uncertainty.score import score_episode
from uncertainty.train import TrainConfig, fit, new_ensemble, train_windows

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here")

SERVICE = PredictorConfig()  # 64 px, the service's default widths
SMALL = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)


@pytest.mark.parametrize("per_member", [False, True])
@pytest.mark.parametrize("config,batch", [(SMALL, 5), (SERVICE, 48)], ids=["16px", "64px"])
def test_fused_forward_equals_members_one_by_one_on_cuda(config, batch, per_member):
    ens = _noisy(Ensemble(config, members=5, seed=1).to("cuda"))
    size = config.image_size
    shape = (5, batch) if per_member else (batch,)
    g = torch.Generator().manual_seed(0)
    ctx = torch.rand(*shape, 2, 3, size, size, generator=g).cuda()
    act = torch.randn(*shape, 2, generator=g).cuda()
    with torch.no_grad():
        fused, loop = ens(ctx, act), ens.forward_loop(ctx, act)
    assert fused.device.type == "cuda" and fused.shape == (5, batch, 3, size, size)
    torch.testing.assert_close(fused, loop, atol=1e-5, rtol=0)
    assert (fused[0] - fused[1]).abs().max() > 1e-3  # members differ


def test_a_model_trained_on_cuda_loads_and_scores_on_the_cpu():
    episodes = [make_episode(seed, "T", steps=12) for seed in range(4)]
    cfg = TrainConfig(members=2, widths=(16, 16, 32), batch_size=8, lr=3e-3, epochs=3, seed=0, device="cuda",
                      progress=False)
    ens = new_ensemble(cfg, episodes)
    assert ens.params[0].device.type == "cuda"
    losses = fit(ens, train_windows(episodes, ens, cfg), cfg)
    assert len(losses) == 3 and losses[-1] < losses[0]

    on_cpu = ensemble_from_bytes(ensemble_to_bytes(ens), device="cpu")
    assert all(p.device.type == "cpu" for p in on_cpu.params)
    for a, b in zip(ens.params, on_cpu.params):
        torch.testing.assert_close(a.detach().cpu(), b, atol=0, rtol=0)  # the weights, bit for bit

    ens.eval()
    probe = make_episode(99, "T", steps=12)
    gpu, cpu = score_episode(ens, probe, top_k=3), score_episode(on_cpu, probe, top_k=3)
    scored = np.isfinite(cpu.per_step)
    assert scored.sum() > 0 and np.array_equal(np.isfinite(gpu.per_step), scored)
    # Other convolution algorithms, other rounding: close, not equal. (A variance of differences: relative errors grow.)
    np.testing.assert_allclose(gpu.per_step[scored], cpu.per_step[scored], rtol=1e-2, atol=1e-7)
