import numpy as np
import pytest
import torch

from tests.uncertainty.synth import make_episode
from uncertainty import model
from uncertainty.ensemble import Ensemble
from uncertainty.errors import ConfigError
from uncertainty.model import PredictorConfig

CFG = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)


def _noisy(ens: Ensemble) -> Ensemble:
    # A fresh output layer is scaled down; make every member's output matter for the comparison.
    with torch.no_grad():
        for p in ens.params:
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())).to(p.device))
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


VAR_CFG = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8, predict_variance=True)


@pytest.mark.parametrize("per_member", [False, True])
def test_fused_variance_head_equals_members_one_by_one(per_member):
    """forward_dist (fused, sliced and whole) gives every member's frame and log-variance as one by one."""
    ens = _noisy(Ensemble(VAR_CFG, members=3, seed=3))
    ens.cpu_slice = 4
    ctx, act = _inputs(9, per_member, seed=2)
    with torch.no_grad():
        frames, logvar = ens.forward_dist(ctx, act)
        loop_frames, loop_logvar = ens.forward_loop(ctx, act, with_variance=True)
        ens.cpu_slice = 0
        whole_frames, whole_logvar = ens.forward_dist(ctx, act)
        plain = ens(ctx, act)
        by_module = [ens.member(k)(ctx[k] if per_member else ctx, act[k] if per_member else act, with_variance=True)
                     for k in range(3)]
    assert frames.shape == logvar.shape == (3, 9, 3, 16, 16)
    for f, lv in ((loop_frames, loop_logvar), (whole_frames, whole_logvar),
                  (torch.stack([m for m, _ in by_module]), torch.stack([v for _, v in by_module]))):
        torch.testing.assert_close(frames, f, atol=1e-5, rtol=0)
        torch.testing.assert_close(logvar, lv, atol=1e-5, rtol=0)
    torch.testing.assert_close(plain, frames, atol=1e-6, rtol=0)  # asking for the variance changes no frame
    assert (logvar[0] - logvar[1]).abs().max() > 1e-3


def test_variance_is_refused_without_a_head():
    ens = Ensemble(CFG, members=2)
    ctx, act = _inputs(2, False, seed=0)
    with pytest.raises(ConfigError, match="no variance head"):
        ens.forward_dist(ctx, act)
    with pytest.raises(ConfigError, match="no variance head"):
        ens.member(0)(ctx, act, with_variance=True)


#: A device parameter for the tests that run on CUDA too (CI has no GPU: bench/device_checks.sh runs them there).
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA here"))]


@pytest.mark.parametrize("device", DEVICES)
def test_fused_gradients_equal_per_member_gradients(device):
    ens = _noisy(Ensemble(CFG, members=2, seed=2).to(device))
    ctx, act = torch.rand(2, 4, 2, 3, 16, 16, device=device), torch.randn(2, 4, 2, device=device)
    ens(ctx, act).pow(2).sum().backward()
    fused = [p.grad.clone() for p in ens.params]
    ens.zero_grad()
    ens.forward_loop(ctx, act).pow(2).sum().backward()
    for a, b in zip(fused, [p.grad for p in ens.params]):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_fused_variance_head_gradients_equal_per_member_gradients():
    ens = _noisy(Ensemble(VAR_CFG, members=2, seed=4))
    ctx, act = torch.rand(2, 4, 2, 3, 16, 16), torch.randn(2, 4, 2)

    def grads(frames_and_logvar):
        ens.zero_grad()
        frames, logvar = frames_and_logvar
        (frames.pow(2).sum() + logvar.sin().sum()).backward()
        return [p.grad.clone() for p in ens.params]

    for a, b in zip(grads(ens.forward_dist(ctx, act)), grads(ens.forward_loop(ctx, act, with_variance=True))):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("fused", [True, False])
def test_only_a_share_of_the_heads_gradient_reaches_the_shared_layers(monkeypatch, fused):
    """The head's gradient into the trunk scales with HEAD_GRAD_SHARE; its own layers get all of theirs."""
    ens = _noisy(Ensemble(VAR_CFG, members=2, seed=5))
    ctx, act = _inputs(3, False, seed=3)

    def head_grads(share):
        monkeypatch.setattr(model, "HEAD_GRAD_SHARE", share)
        ens.zero_grad()
        out = ens.forward_dist(ctx, act) if fused else ens.forward_loop(ctx, act, with_variance=True)
        out[1].sum().backward()
        return {n: torch.zeros_like(p) if p.grad is None else p.grad.clone() for n, p in zip(ens.names, ens.params)}

    full, part, none = head_grads(1.0), head_grads(0.3), head_grads(0.0)
    for name in ("enc1.weight", "dec1.weight"):
        assert full[name].abs().max() > 0
        torch.testing.assert_close(part[name], 0.3 * full[name], atol=1e-6, rtol=1e-4)
        assert not none[name].any()
    assert not full["out.weight"].any()                         # the frame's own output layer: untouched
    torch.testing.assert_close(part["var_out.weight"], full["var_out.weight"])


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
