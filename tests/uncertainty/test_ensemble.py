import numpy as np
import pytest
import torch

from tests.uncertainty.synth import make_episode
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig

CFG = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)


def _noisy(ens: Ensemble) -> Ensemble:
    # A fresh output layer is scaled down; make every member's output matter for the comparison.
    with torch.no_grad():
        for p in ens.params:
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    return ens


def _inputs(batch: int, per_member: bool, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Contexts (B,2,3,16,16) and actions (B,2), or one set per member (3,B,...), seeded."""
    g = torch.Generator().manual_seed(seed)
    shape = (3, batch) if per_member else (batch,)
    return torch.rand(*shape, 2, 3, 16, 16, generator=g), torch.randn(*shape, 2, generator=g)


@pytest.mark.parametrize("per_member", [False, True])
def test_fused_forward_equals_members_one_by_one(per_member):
    ens = _noisy(Ensemble(CFG, members=3, seed=1))
    ctx, act = _inputs(5, per_member, seed=0)
    with torch.no_grad():
        fused = ens(ctx, act)
        loop = ens.forward_loop(ctx, act)
        vmapped = ens.forward_vmap(ctx, act)
        by_module = torch.stack([ens.member(k)(ctx[k] if per_member else ctx, act[k] if per_member else act)
                                 for k in range(3)])
    assert fused.shape == (3, 5, 3, 16, 16)
    torch.testing.assert_close(fused, loop, atol=1e-5, rtol=0)
    torch.testing.assert_close(vmapped, loop, atol=1e-5, rtol=0)
    torch.testing.assert_close(by_module, loop, atol=1e-5, rtol=0)
    assert (fused[0] - fused[1]).abs().max() > 1e-3  # members differ


@pytest.mark.parametrize("per_member", [False, True])
def test_cpu_slices_give_the_whole_batch_result(per_member):
    """A batch larger than cpu_slice (with a short last slice) goes through in slices, same numbers."""
    ens = _noisy(Ensemble(CFG, members=3, seed=2))
    ens.cpu_slice = 8
    ctx, act = _inputs(19, per_member, seed=1)
    with torch.no_grad():
        sliced = ens(ctx, act)
        loop = ens.forward_loop(ctx, act)
        ens.cpu_slice = 0
        whole = ens(ctx, act)
    assert sliced.shape == (3, 19, 3, 16, 16)
    torch.testing.assert_close(sliced, whole, atol=1e-6, rtol=0)
    torch.testing.assert_close(sliced, loop, atol=1e-5, rtol=0)


def test_fused_gradients_equal_per_member_gradients():
    ens = _noisy(Ensemble(CFG, members=2, seed=2))
    ctx, act = torch.rand(2, 4, 2, 3, 16, 16), torch.randn(2, 4, 2)
    ens(ctx, act).pow(2).sum().backward()
    fused = [p.grad.clone() for p in ens.params]
    ens.zero_grad()
    ens.forward_loop(ctx, act).pow(2).sum().backward()
    for a, b in zip(fused, [p.grad for p in ens.params]):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_same_seed_same_weights_other_seed_other_weights():
    a, b, c = Ensemble(CFG, 2, seed=5), Ensemble(CFG, 2, seed=5), Ensemble(CFG, 2, seed=6)
    assert all(torch.equal(x, y) for x, y in zip(a.params, b.params))
    assert not all(torch.equal(x, y) for x, y in zip(a.params, c.params))


@pytest.mark.parametrize("horizon", [1, 3])
def test_disagreement_marks_steps_without_context_or_successors(horizon):
    ep = make_episode(0, steps=10)
    ens = _noisy(Ensemble(CFG, members=2, seed=0))
    d = ens.disagreement(ep.frames, ep.actions, horizon=horizon)
    assert d.shape == (10,)
    valid = np.arange(1, 10 - horizon)
    assert np.isnan(d[0]) and np.all(np.isnan(d[10 - horizon:]))
    assert np.all(np.isfinite(d[valid])) and np.all(d[valid] > 0)
    np.testing.assert_allclose(d, ens.disagreement(ep.frames, ep.actions, horizon=horizon, fused=False),
                               rtol=1e-4, atol=1e-9)
