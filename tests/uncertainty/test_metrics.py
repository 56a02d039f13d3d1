import numpy as np
import pytest
import torch

from uncertainty import metrics as M


def reference_ssim(x: np.ndarray, y: np.ndarray, win: int = 11, sigma: float = 1.5) -> float:
    """Wang et al. (2004), written out: one Gaussian-weighted window per valid pixel, per channel."""
    ax = np.arange(win) - (win - 1) / 2
    g = np.exp(-ax ** 2 / (2 * sigma ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    values = []
    for ch in range(x.shape[0]):
        for i in range(x.shape[1] - win + 1):
            for j in range(x.shape[2] - win + 1):
                a, b = x[ch, i:i + win, j:j + win], y[ch, i:i + win, j:j + win]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
                cov = (w * (a - ma) * (b - mb)).sum()
                values.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2)))
    return float(np.mean(values))


def test_ssim_matches_the_written_out_reference():
    rng = np.random.default_rng(0)
    x = rng.random((2, 3, 16, 16))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    ours = M.ssim(torch.tensor(x), torch.tensor(y)).numpy()
    for n in range(2):
        assert ours[n] == pytest.approx(reference_ssim(x[n], y[n]), abs=1e-10)


def test_ssim_identities():
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.random((1, 3, 16, 16)))
    assert M.ssim(x, x).item() == pytest.approx(1.0)
    assert M.ssim(x, 1 - x).item() < 0  # anti-correlated structure
    const = torch.full_like(x, 0.5)
    assert M.ssim(const, const + 0.1).item() < 1.0
    with pytest.raises(ValueError, match="at least 11x11"):
        M.ssim(x[..., :8, :8], x[..., :8, :8])


def test_mse_and_psnr_known_values():
    a = torch.zeros(2, 3, 4, 4)
    b = torch.full((2, 3, 4, 4), 0.1)
    assert M.mse(a, b).tolist() == pytest.approx([0.01, 0.01])
    assert M.psnr(a, b).tolist() == pytest.approx([20.0, 20.0])
    assert M.psnr_from_mse(0.001) == pytest.approx(30.0)


def test_spearman():
    a = np.arange(10.0)
    assert M.spearman(a, a ** 3) == pytest.approx(1.0)
    assert M.spearman(a, -a) == pytest.approx(-1.0)
    assert np.isnan(M.spearman(a, np.ones(10)))
    with_nan = np.append(a, np.nan)
    assert M.spearman(with_nan, np.append(a, 3.0)) == pytest.approx(1.0)


def test_sparsification_needs_an_uncertainty_that_ranks_something():
    err = np.array([5.0, 1.0, 4.0, 2.0])
    flat = M.sparsification(np.zeros(4), err)  # one member: no disagreement anywhere
    assert np.isnan(flat["curve"]).all() and np.isnan(M.sparsification_error(flat))
    # Pairs with a NaN are left out, as spearman leaves them out: the rest still ranks perfectly.
    with_nan = M.sparsification(np.array([5.0, np.nan, 4.0, 2.0]), err)
    assert M.sparsification_error(with_nan) == pytest.approx(0.0)


def test_sparsification_curve_and_oracle():
    err = np.array([5.0, 1.0, 4.0, 2.0, 3.0, 0.0, 9.0, 7.0, 6.0, 8.0])
    perfect = M.sparsification(err, err)
    assert perfect["curve"] == perfect["oracle"]
    assert perfect["curve"][0] == pytest.approx(err.mean())
    assert all(a >= b for a, b in zip(perfect["curve"], perfect["curve"][1:]))
    assert M.sparsification_error(perfect) == pytest.approx(0.0)
    backwards = M.sparsification(-err, err)
    assert all(c >= o for c, o in zip(backwards["curve"], backwards["oracle"]))
    assert M.sparsification_error(backwards) > 0.5
