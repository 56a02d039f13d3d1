"""Image and calibration metrics: MSE, PSNR, SSIM (our own, Wang et al. 2004), Spearman, sparsification.

Images are float arrays or tensors in [0, 1] shaped (..., 3, H, W); every metric
returns one value per leading index so callers can average or rank per sample.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import spearmanr as _scipy_spearman
from torch.nn import functional as F

#: SSIM constants of Wang et al. (2004) for a data range of 1.
SSIM_K1, SSIM_K2 = 0.01, 0.03
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error per sample: (N, ...) -> (N,)."""
    return (pred - target).pow(2).flatten(1).mean(dim=1)


def psnr(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for a data range of 1, per sample: (N, ...) -> (N,)."""
    return 10.0 * torch.log10(1.0 / (mse(pred, target) + eps))


def psnr_from_mse(m: float, eps: float = 1e-10) -> float:
    """PSNR in dB of a (mean) MSE value."""
    return float(10.0 * np.log10(1.0 / (m + eps)))


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Normalised 1-D Gaussian (size,), float64."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = SSIM_WINDOW,
         sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Mean structural similarity per sample, per channel then averaged: (N, C, H, W) -> (N,).

    Gaussian-weighted local statistics (separable window, ``valid`` region only,
    as in Wang et al.'s reference code), data range 1, population covariances.
    Raises ``ValueError`` when the images are smaller than the window.
    """
    if pred.shape != target.shape or pred.dim() != 4:
        raise ValueError(f"ssim expects two (N,C,H,W) tensors of one shape, found {tuple(pred.shape)} "
                         f"and {tuple(target.shape)}")
    n, c, h, w = pred.shape
    if h < window or w < window:
        raise ValueError(f"ssim needs images of at least {window}x{window}, found {h}x{w}")
    g = gaussian_window(window, sigma).to(device=pred.device, dtype=pred.dtype)  # (win,)
    gx = g.view(1, 1, 1, window).expand(c, 1, 1, window)        # (C, 1, 1, win)
    gy = g.view(1, 1, window, 1).expand(c, 1, window, 1)        # (C, 1, win, 1)

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(x, gx, groups=c), gy, groups=c)  # (N, C, H-win+1, W-win+1)

    mu_x, mu_y = blur(pred), blur(target)
    sxx = blur(pred * pred) - mu_x ** 2
    syy = blur(target * target) - mu_y ** 2
    sxy = blur(pred * target) - mu_x * mu_y
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    smap = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))
    return smap.flatten(1).mean(dim=1)                           # (N,)


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation of two 1-D arrays (NaN pairs dropped); NaN when undefined."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return float("nan")
    return float(_scipy_spearman(a[ok], b[ok]).statistic)


def sparsification(uncertainty: np.ndarray, error: np.ndarray,
                   fractions: tuple[float, ...] = tuple(i / 10 for i in range(10))) -> dict[str, list[float]]:
    """Sparsification curve: mean error of the samples left after removing the most uncertain fraction.

    Returns {"fractions", "curve", "oracle"}; the oracle removes by the true error,
    so the gap between the two (its area, ``sparsification_error``) measures how
    well the uncertainty ranks the errors. NaN curves when the uncertainty ranks nothing (all
    equal, or no finite pair). Raises ``ValueError`` on mismatched or empty input.
    """
    u, e = np.asarray(uncertainty, np.float64), np.asarray(error, np.float64)
    if u.shape != e.shape or u.ndim != 1 or len(u) == 0:
        raise ValueError(f"sparsification expects two equal non-empty 1-D arrays, found {u.shape} and {e.shape}")
    finite = np.isfinite(u) & np.isfinite(e)  # as spearman: pairs with a NaN are left out
    u, e = u[finite], e[finite]
    if len(u) == 0 or np.ptp(u) == 0:  # nothing to rank by (e.g. one member: no disagreement)
        nan = [float("nan")] * len(fractions)
        return {"fractions": [float(f) for f in fractions], "curve": nan, "oracle": nan}
    by_u = e[np.argsort(-u, kind="stable")]                      # errors, most uncertain first
    by_e = np.sort(e)[::-1]                                      # errors, largest first
    curve, oracle = [], []
    for f in fractions:
        drop = int(round(f * len(e)))
        keep = max(len(e) - drop, 1)
        curve.append(float(by_u[len(e) - keep:].mean()))
        oracle.append(float(by_e[len(e) - keep:].mean()))
    return {"fractions": [float(f) for f in fractions], "curve": curve, "oracle": oracle}


def sparsification_error(curve: dict[str, list[float]]) -> float:
    """Mean gap between the curve and its oracle, normalised by the full-set error (0 is perfect)."""
    base = curve["curve"][0] or 1.0
    return float(np.mean(np.asarray(curve["curve"]) - np.asarray(curve["oracle"])) / base)
