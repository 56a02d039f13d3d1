"""Training a candidate ensemble on a catalog snapshot, evaluating it on the pinned eval split.

``train_candidate`` is the whole retrain job: load the train snapshot, fit the
members (one fused forward and backward per step; each member draws its own
shuffled batch), evaluate on the eval split, register the candidate and run it
through the registry's promotion gate. A warm start (``--from-champion``) begins from the
champion's weights, or from ``warm_start``'s choice when they are damaged.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from storage.checkpoint_files import raise_unless_lasting
from storage.errors import CorruptCheckpointError, RegistryUnavailableError
from storage.gate import GateDecision
from storage.models import ModelRegistry
from storage.records import Episode
from uncertainty import metrics as M
from uncertainty.checkpoint import load_ensemble, save_candidate
from uncertainty.config import TrainConfig  # defined torch-free for the CLI; importable from here too
from uncertainty.data import (CatalogLike, Windows, action_stats, build_windows, load_eval, load_train,
                              member_indices)
from uncertainty.ensemble import Ensemble, default_device
from uncertainty.errors import CheckpointError, ConfigError, DataError, DivergedError
from uncertainty.model import PredictorConfig

log = logging.getLogger(__name__)


def resolve_device(device: str) -> torch.device:
    """The torch device a ``TrainConfig.device`` names ("auto": CUDA if available, else CPU).

    Raises ``ConfigError`` when "cuda" is asked for and torch sees no CUDA device.
    """
    if device == "auto":
        return default_device()
    if device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device cuda requested but torch sees no CUDA device")
    return torch.device(device)


@dataclass
class TrainResult:
    """What a retrain produced: the registered version, its metrics, and the gate's decision."""

    version: str
    metrics: dict[str, Any]
    decision: GateDecision
    losses: list[float] = field(default_factory=list)
    """Mean training loss per epoch."""
    quarantined: list[str] = field(default_factory=list)
    """Train episodes whose files were found missing or damaged, quarantined and left out."""
    warnings: list[str] = field(default_factory=list)
    """One line each for what the run did other than asked: train episodes left out as replays of eval episodes
    (``train_replays_left_out`` in the metrics), a warm start from another model than the champion (or none),
    settings a warm start overrode (also logged, and in the metrics as ``warm_start_*``)."""


def _show_progress(flag: bool | None) -> bool:
    return sys.stderr.isatty() if flag is None else flag


def _clip_per_member(params: list[torch.Tensor], max_norm: float) -> None:
    """Scales each member's gradients (slices along dim 0) to a norm of at most ``max_norm``."""
    sq = sum(p.grad.pow(2).flatten(1).sum(dim=1) for p in params)        # (K,)
    scale = (max_norm / (sq.sqrt() + 1e-6)).clamp(max=1.0)               # (K,)
    for p in params:
        p.grad.mul_(scale.view(-1, *([1] * (p.dim() - 1))))


def variance_loss(mean: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-member loss of a variance head: (K,B,3,H,W) each -> (K,).

    The beta-NLL of Seitzer et al. (2022) with beta = 1: the Gaussian NLL of the target, each pixel
    weighted by its (constant) predicted variance, so its gradient, (variance - squared error) / 2
    per pixel, is on the scale of the squared error and lets no pixel dominate. The mean is detached:
    it learns from the squared error alone, the head learns to predict that error.
    """
    sq = (mean.detach() - target).pow(2)                                   # (K, B, 3, H, W)
    nll = 0.5 * (logvar + sq * torch.exp(-logvar))                         # (K, B, 3, H, W)
    return (torch.exp(logvar).detach() * nll).mean(dim=(1, 2, 3, 4))      # (K,)


def _check_finite(loss: float, epoch: int, epochs: int, step: int, steps: int, lr: float) -> None:
    if not math.isfinite(loss):
        raise DivergedError(f"training diverged: the loss is {loss} at epoch {epoch + 1} of {epochs}, step "
                            f"{step + 1} of {steps} (learning rate {lr:g}); train again with a lower learning rate")


def fit(ensemble: Ensemble, windows: Windows, cfg: TrainConfig,
        on_epoch: Callable[[int, float], None] | None = None) -> list[float]:
    """Train all members in place on ``windows`` (horizon 1); returns the mean loss of each epoch.

    Every step draws, for each member, its own batch from its own seeded order
    (the same seed gives the same weights), and runs one fused forward/backward.
    The returned losses are the squared error alone, also with a variance head
    (whose ``variance_loss`` is added to what is minimised). Raises ``DivergedError`` at the first
    step whose loss is not finite, before it updates the weights (a NaN model is no candidate).
    """
    if windows.horizon != 1:
        raise DataError(f"training needs horizon-1 windows, found horizon {windows.horizon}")
    rng = np.random.default_rng(cfg.seed)
    k, b, device = ensemble.members, cfg.batch_size, ensemble.device
    variance = ensemble.config.predict_variance
    pools = member_indices(windows, k, cfg.bootstrap, rng)
    # A batch larger than a member's pool only repeats its windows (np.resize below) and allocates
    # batch_size frames per step: --batch-size 10**7 on 40 windows was a MemoryError traceback.
    b = min(b, max(len(p) for p in pools))
    steps = max(1, math.ceil(max(len(p) for p in pools) / b))
    opt = torch.optim.Adam(ensemble.params.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps * cfg.epochs, eta_min=cfg.lr / 10)
    losses = []
    ensemble.train()
    bar = tqdm(total=steps * cfg.epochs, desc="train", unit="step", disable=not _show_progress(cfg.progress),
               file=sys.stderr, dynamic_ncols=True)
    try:
        for epoch in range(cfg.epochs):
            orders = [np.resize(rng.permutation(p), steps * b) for p in pools]  # (steps*B,) per member
            order = torch.as_tensor(np.stack(orders).reshape(k, steps, b))      # (K, steps, B)
            total = 0.0
            for s in range(steps):
                ctx, act, tgt = windows.batch(order[:, s], device)  # (K,B,C,3,H,W), (K,B,1,A), (K,B,1,3,H,W)
                a = ensemble.normalize_actions(act[:, :, 0])                       # (K, B, A)
                if variance:
                    pred, logvar = ensemble.forward_dist(ctx, a)                   # (K, B, 3, H, W) each
                else:
                    pred = ensemble(ctx, a)                                        # (K, B, 3, H, W)
                # Sum over members of each member's mean loss: every member learns as if alone.
                mse = (pred - tgt[:, :, 0]).pow(2).mean(dim=(1, 2, 3, 4)).sum()
                loss = mse + variance_loss(pred, logvar, tgt[:, :, 0]).sum() if variance else mse
                _check_finite(loss.item(), epoch, cfg.epochs, s, steps, cfg.lr)  # before NaN reaches the weights
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if cfg.grad_clip is not None:
                    _clip_per_member(list(ensemble.params), cfg.grad_clip)
                opt.step()
                sched.step()
                total += mse.item() / k
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{total / (s + 1):.2e}")
            losses.append(total / steps)
            if on_epoch is not None:
                on_epoch(epoch, losses[-1])
    finally:
        bar.close()
        ensemble.eval()
    return losses


@torch.inference_mode()
def _rollout_stats(ensemble: Ensemble, windows: Windows, batch_size: int,
                   predicted: bool = False) -> dict[str, np.ndarray]:
    """Per-window, per-horizon-step arrays (N, H): mean's mse/ssim, copy-last mse/ssim, disagreement.

    ``predicted`` (horizon-1 windows, a variance head): also "predicted" (N,), the members' mean
    predicted variance, from the same forward pass as the frames.
    """
    if predicted and windows.horizon != 1:
        raise DataError(f"predicted variances are taken on horizon-1 windows, found horizon {windows.horizon}")
    out: dict[str, list] = {"mse": [], "ssim": [], "base_mse": [], "base_ssim": [], "var": []}
    if predicted:
        out["predicted"] = []
    for lo in range(0, len(windows), batch_size):
        idx = torch.arange(lo, min(lo + batch_size, len(windows)))
        ctx, act, tgt = windows.batch(idx, ensemble.device)  # (B,C,3,H,W), (B,H,A), (B,H,3,H,W)
        a = ensemble.normalize_actions(act)                              # (B, H, A)
        if predicted:  # the one step of a horizon-1 rollout, with the log-variances
            frames, logvar = ensemble.forward_dist(ctx, a[:, 0])         # (K, B, 3, H, W) each
            preds = frames.clamp(0.0, 1.0)[:, :, None]                   # (K, B, 1, 3, H, W)
            out["predicted"].append(logvar.exp().mean(dim=(0, 2, 3, 4)).double().cpu().numpy())  # (B,)
        else:
            preds = ensemble.rollout(ctx, a)                             # (K, B, H, 3, H, W)
        mean = preds.mean(dim=0)                                         # (B, H, 3, H, W)
        var = preds.var(dim=0, unbiased=False).mean(dim=(2, 3, 4))      # (B, H)
        last = ctx[:, -1]                                                # (B, 3, H, W)
        cols: dict[str, list] = {key: [] for key in out if key not in ("var", "predicted")}
        for h in range(windows.horizon):
            cols["mse"].append(M.mse(mean[:, h], tgt[:, h]))
            cols["ssim"].append(M.ssim(mean[:, h], tgt[:, h]))
            cols["base_mse"].append(M.mse(last, tgt[:, h]))
            cols["base_ssim"].append(M.ssim(last, tgt[:, h]))
        for key, col in cols.items():
            out[key].append(torch.stack(col, dim=1).double().cpu().numpy())  # (B, H)
        out["var"].append(var.double().cpu().numpy())
    return {key: np.concatenate(v) for key, v in out.items()}


def _horizon_metrics(stats: dict[str, np.ndarray], col: int, h: int) -> dict[str, float]:
    m = float(stats["mse"][:, col].mean())
    base = float(stats["base_mse"][:, col].mean())
    return {f"h{h}_mse": m, f"h{h}_psnr": M.psnr_from_mse(m), f"h{h}_ssim": float(stats["ssim"][:, col].mean()),
            f"h{h}_disagreement": float(stats["var"][:, col].mean()),
            f"baseline_h{h}_mse": base, f"baseline_h{h}_psnr": M.psnr_from_mse(base),
            f"baseline_h{h}_ssim": float(stats["base_ssim"][:, col].mean()),
            f"h{h}_psnr_gain_db": M.psnr_from_mse(m) - M.psnr_from_mse(base)}


def _longer_horizons(ensemble: Ensemble, episodes: Sequence[Episode], horizons: Sequence[int], rollout_stride: int,
                     batch_size: int) -> dict[str, Any]:
    """The metrics of the horizons past 1, each from a rollout over every episode long enough for it: one rollout
    as long as the longest horizon serves the shorter ones its episodes all reach (one rollout where the episodes
    are of one length; another where some reach a shorter horizon only); NaN mse, psnr and ssim for a horizon
    every episode is too short for."""
    out: dict[str, Any] = {}
    reach = {h: sum(len(ep) >= ensemble.config.context + h for ep in episodes) for h in horizons if h > 1}
    longer = sorted(reach)
    while longer:
        if not reach[h := longer[-1]]:  # no episode long enough: this one is NaN, a shorter one may be measured
            out.update({f"h{h}_{k}": float("nan") for k in ("mse", "psnr", "ssim")})
            longer.pop()
            continue
        served = [h for h in longer if reach[h] == reach[longer[-1]]]
        wl = build_windows(episodes, ensemble.config, horizon=longer[-1], stride=rollout_stride)
        sl = _rollout_stats(ensemble, wl, batch_size)
        for h in served:
            out.update(_horizon_metrics(sl, h - 1, h))
        out[f"h{longer[-1]}_windows"] = len(wl)
        longer = [h for h in longer if h not in served]
    return out


def evaluate_episodes(ensemble: Ensemble, episodes: Sequence[Episode], eval_hash: str,
                      horizons: Sequence[int] = (1, 5, 10), rollout_stride: int = 5,
                      batch_size: int = 64) -> dict[str, Any]:
    """Accuracy and calibration of the ensemble mean on ``episodes``.

    Horizon 1 uses every window; longer horizons roll each member out on its own
    predictions from every ``rollout_stride``-th step (NaN for a horizon every episode is
    too short for). PSNR is computed from the mean MSE (a copy-last baseline can have zero
    error on a static frame, which would make per-frame PSNR infinite).
    Calibration: Spearman between per-window disagreement and the mean's error at
    horizon 1, and the sparsification curve with its oracle. With a variance head
    also the same for the total predictive variance (disagreement plus the members'
    mean predicted variance: the variance of the mixture), and the ratio of its
    mean to the mean error (1 when its scale is right; None when the error is 0).
    """
    cfg = ensemble.config
    w1 = build_windows(episodes, cfg, horizon=1)
    s1 = _rollout_stats(ensemble, w1, batch_size, predicted=cfg.predict_variance)
    out: dict[str, Any] = {"eval_split_hash": eval_hash, "eval_episodes": len(episodes), "eval_windows": len(w1)}
    out.update(_horizon_metrics(s1, 0, 1))
    out.update(_longer_horizons(ensemble, episodes, horizons, rollout_stride, batch_size))
    var, err = s1["var"][:, 0], s1["mse"][:, 0]
    out["spearman"] = M.spearman(var, err)
    curve = M.sparsification(var, err)
    out["sparsification"] = curve
    out["sparsification_error"] = M.sparsification_error(curve)
    if "predicted" in s1:
        total = var + s1["predicted"]
        out["h1_predicted_variance"] = float(s1["predicted"].mean())
        out["spearman_predicted_variance"] = M.spearman(s1["predicted"], err)
        out["spearman_total"] = M.spearman(total, err)
        out["sparsification_total"] = M.sparsification(total, err)
        out["sparsification_error_total"] = M.sparsification_error(out["sparsification_total"])
        # No error to compare with: None, not NaN, which the gate (it checks every h1_ number) would refuse.
        out["h1_total_variance_ratio"] = float(total.mean() / err.mean()) if err.mean() > 0 else None
    return out


def evaluate(ensemble: Ensemble, catalog: CatalogLike, **kwargs: Any) -> dict[str, Any]:
    """``evaluate_episodes`` on the catalog's pinned eval split (never the train split).

    Raises ``DataError`` when no eval split is pinned or the ensemble cannot be evaluated on it
    (``check_evaluable``).
    """
    episodes, eval_hash = load_eval(catalog)
    check_evaluable(ensemble.config, episodes)
    return evaluate_episodes(ensemble, episodes, eval_hash, **kwargs)


def new_ensemble(cfg: TrainConfig, episodes: Sequence[Episode]) -> Ensemble:
    """A fresh ensemble shaped for ``episodes`` (image size from their frames), normalised on their actions."""
    if not episodes:
        raise DataError("cannot build an ensemble for zero episodes")
    pcfg = PredictorConfig(image_size=int(episodes[0].frames.shape[1]), context=cfg.context, widths=cfg.widths,
                           predict_variance=cfg.variance_head)
    ens = Ensemble(pcfg, members=cfg.members, seed=cfg.seed)
    ens.set_action_stats(*action_stats(episodes))
    return ens.to(resolve_device(cfg.device))


def train_windows(episodes: Sequence[Episode], ensemble: Ensemble, cfg: TrainConfig) -> Windows:
    """Horizon-1 training windows of ``episodes``, capped at ``cfg.max_windows`` (seeded subset)."""
    windows = build_windows(episodes, ensemble.config, horizon=1)
    if cfg.max_windows is not None and len(windows) > cfg.max_windows:
        rng = np.random.default_rng(cfg.seed + 1)
        windows = windows.subset(np.sort(rng.choice(len(windows), cfg.max_windows, replace=False)))
    return windows


def check_evaluable(config: PredictorConfig, eval_episodes: Sequence[Episode]) -> None:
    """Raises ``DataError`` unless a model of ``config`` can be evaluated on ``eval_episodes``.

    Their frames must have the model's size, that size must hold one SSIM window, and one of them at least
    must be long enough for the model's context frames and a frame to predict.
    """
    sizes = sorted({int(ep.frames.shape[1]) for ep in eval_episodes})
    if sizes != [config.image_size]:
        raise DataError(f"the eval split has {'/'.join(map(str, sizes))}px frames, the model {config.image_size}px: "
                        "train on episodes of the eval split's size (its pinned split is never replaced: a "
                        "model of another size needs a data directory of its own)")
    if config.image_size < M.SSIM_WINDOW:
        raise DataError(f"{config.image_size}px frames are too small to evaluate: SSIM needs at least "
                        f"{M.SSIM_WINDOW}x{M.SSIM_WINDOW}")
    longest = max(len(ep) for ep in eval_episodes)
    if longest <= config.context:
        raise DataError(f"the eval split's episodes are too short to evaluate a model of context {config.context}: "
                        f"the longest has {longest} frame(s), it needs {config.context + 1} (its context frames "
                        "and the one it predicts)")


@dataclass
class WarmStart:
    """Where a ``--from-champion`` training starts: a registered model's weights, or a fresh model."""

    ensemble: Ensemble | None
    """The weights to fine-tune (None: train a fresh model)."""
    version: str | None
    """The model they are (None for a fresh model)."""
    note: str | None = None
    """Why it is not the champion, in one line (None when it is)."""


def _rollback_chain(registry: ModelRegistry, champion: str) -> list[str]:
    """The earlier champions ``ModelRegistry.rollback`` walks back to, newest first."""
    live = [e.version for e in registry.history() if e.rolled_back_at is None]
    return list(dict.fromkeys(v for v in reversed(live) if v != champion))


def _load_parent(registry: ModelRegistry, version: str, device: torch.device) -> Ensemble:
    """``load_ensemble``, with a read that failed and may pass raised as ``RegistryUnavailableError``."""
    try:
        return load_ensemble(registry, version, device)
    except CheckpointError:  # bytes read and matching their sha256, yet no ensemble: a verdict
        raise
    except CorruptCheckpointError as exc:
        raise_unless_lasting(exc, f"warm-start from {version}")
        raise


def warm_start(registry: ModelRegistry, device: torch.device) -> WarmStart:
    """The champion's weights to fine-tune; when its checkpoint is damaged for good (its sha256, missing,
    pruned, not an ensemble), the newest sound model of its rollback chain, or else none (a fresh model), so
    that the gate can replace a damaged champion rather than every warm-started job failing on it.

    Raises ``ConfigError`` when there is no champion and ``RegistryUnavailableError`` when a checkpoint
    cannot be read now (an I/O error, which may pass: nothing is trained; the same job may succeed later).
    """
    champion = registry.champion()
    if champion is None:
        raise ConfigError("--from-champion given but there is no champion yet")
    try:
        return WarmStart(_load_parent(registry, champion, device), champion)
    except CorruptCheckpointError as exc:
        damage = f"champion {champion} cannot be loaded ({exc})"
    for version in _rollback_chain(registry, champion):
        try:
            ensemble = _load_parent(registry, version, device)
        except CorruptCheckpointError:
            continue
        return WarmStart(ensemble, version, f"{damage}: warm-started from {version}, the newest sound model "
                                            "of its rollback chain")
    return WarmStart(None, None, f"{damage}, nor any earlier champion: trained a fresh model")


def warm_start_overrides(cfg: TrainConfig, ensemble: Ensemble) -> list[str]:
    """The shape settings of ``cfg`` a warm start from ``ensemble`` does not take (it keeps its own), as
    ``"members 3 (kept 2)"``."""
    def shown(value: Any) -> str:
        return ",".join(map(str, value)) if isinstance(value, (tuple, list)) else str(value)
    pcfg = ensemble.config
    pairs = {"members": (cfg.members, ensemble.members), "context": (cfg.context, pcfg.context),
             "widths": (tuple(cfg.widths), tuple(pcfg.widths)),
             "variance_head": (cfg.variance_head, pcfg.predict_variance)}
    return [f"{name} {shown(asked)} (kept {shown(kept)})" for name, (asked, kept) in pairs.items() if asked != kept]


def _label(start: WarmStart) -> str:
    return f"champion {start.version}" if start.note is None else f"{start.version} (for the damaged champion)"


def check_warm_start(start: WarmStart, cfg: TrainConfig, image_size: int) -> None:
    """Raises ``ConfigError`` when ``start``'s model cannot be trained as asked: shaped for other images than
    ``image_size``, or without the variance head ``cfg`` asks for."""
    if start.ensemble is None:
        return
    if start.ensemble.config.image_size != image_size:
        raise ConfigError(f"{_label(start)} predicts {start.ensemble.config.image_size}px frames, the train snapshot "
                          f"has {image_size}px")
    if cfg.variance_head and not start.ensemble.config.predict_variance:
        raise ConfigError(f"{_label(start)} has no variance head to warm-start: "
                          "train a fresh model for one (without --from-champion)")


def starting_point(cfg: TrainConfig, episodes: Sequence[Episode],
                   start: WarmStart | None) -> tuple[Ensemble, dict[str, Any], list[str]]:
    """The ensemble to train, what to record of where it started, and the warnings to give.

    A fresh model without a ``start`` (``warm_start``'s, for ``cfg.from_champion``); else its model, checked
    against ``episodes``. The record (for the metrics and the train config): ``warm_start_from`` (the version,
    None for a fresh model), and when there is one to give ``warm_start_note`` (why not the champion) and
    ``warm_start_overrode`` (``warm_start_overrides``); each warning is logged. Raises ``ConfigError``
    (a model shaped for other images or without the variance head asked for).
    """
    if start is None:
        return new_ensemble(cfg, episodes), {}, []
    record: dict[str, Any] = {"warm_start_from": start.version}
    warnings = []
    if start.note is not None:
        record["warm_start_note"] = start.note
        warnings.append(start.note)
    if start.ensemble is None:
        ensemble = new_ensemble(cfg, episodes)
    else:
        ensemble = start.ensemble
        check_warm_start(start, cfg, int(episodes[0].frames.shape[1]))
        overrode = warm_start_overrides(cfg, ensemble)
        if overrode:
            record["warm_start_overrode"] = "; ".join(overrode)
            warnings.append(f"warm start from {start.version} keeps its shape, not the one asked for: "
                            f"{record['warm_start_overrode']}")
    for line in warnings:
        log.warning("%s", line)
    return ensemble, record, warnings


def train_candidate(catalog: CatalogLike, registry: ModelRegistry, cfg: TrainConfig) -> TrainResult:
    """Train on the train snapshot, evaluate on the eval split, register, and run the gate.

    With ``cfg.from_champion`` training starts from the champion (or, when its checkpoint is damaged, where
    ``starting_point`` says; ``TrainResult.warnings`` tells; as it does of train episodes left out, replays of
    eval episodes and, in a catalog from before it held one frame size, episodes of another size than the eval
    split's). Raises ``DataError`` (no train data, no eval split, eval episodes in the snapshot, an eval split
    the model cannot be evaluated on), ``ConfigError`` (warm start without a champion, or from one shaped for
    other images or without the variance head asked for), ``DivergedError`` (a non-finite loss: nothing is
    registered), ``RegistryUnavailableError`` (a checkpoint to warm-start from cannot be read now) and the
    registry's errors.
    """
    registry.check_ready(champion=not cfg.from_champion)  # a read-only models/, an unreadable champion: now
    pinned = catalog.eval_split() is not None  # without one, load_train's errors (no train episodes) come first
    eval_episodes, eval_hash = load_eval(catalog) if pinned else ([], "")
    sizes = {int(ep.frames.shape[1]) for ep in eval_episodes}  # more than one: check_evaluable refuses the split
    # A warm start refused (no champion, no variance head, other images) before the train snapshot is read: that
    # read quarantines damaged episodes, which a job that cannot start must leave where they are.
    warm = warm_start(registry, resolve_device(cfg.device)) if cfg.from_champion else None
    if warm is not None and len(sizes) == 1:
        check_warm_start(warm, cfg, min(sizes))
    data = load_train(catalog, cfg.max_episodes, image_size=min(sizes) if len(sizes) == 1 else None)
    if not pinned:
        eval_episodes, eval_hash = load_eval(catalog)  # raises DataError: no eval split is pinned
    ensemble, record, warnings = starting_point(cfg, data.episodes, warm)
    check_evaluable(ensemble.config, eval_episodes)  # before training, not after it
    windows = train_windows(data.episodes, ensemble, cfg)
    start = time.perf_counter()
    losses = fit(ensemble, windows, cfg)
    train_s = time.perf_counter() - start
    metrics = evaluate_episodes(ensemble, eval_episodes, eval_hash, rollout_stride=cfg.eval_rollout_stride)
    metrics.update({"train_episodes": len(data.episodes), "train_replays_left_out": len(data.replays),
                    "train_other_size_left_out": len(data.other_size),
                    "train_windows": len(windows),
                    "train_seconds": round(train_s, 2), "train_threads": torch.get_num_threads(),
                    "train_loss": losses[-1], "epochs": cfg.epochs} | record)
    # A warm start keeps its model's shape: record what was trained, not what was asked for.
    used = cfg.to_dict() | {"members": ensemble.members, "context": ensemble.config.context,
                            "widths": list(ensemble.config.widths),
                            "variance_head": ensemble.config.predict_variance} | record
    version = save_candidate(registry, ensemble, metrics, data.snapshot_id, eval_hash,
                             parent=record.get("warm_start_from"), train_config=used, snapshot=data.snapshot)
    try:
        decision = registry.gate(version, cfg.min_rel_improvement, eval_split_hash=eval_hash)
    except RegistryUnavailableError as exc:  # ("nothing changed" is the gate's: the job registered a candidate)
        raise RegistryUnavailableError(f"registered {version} but cannot gate it now: {exc.__cause__ or exc}; the "
                                       f"champion is as it was, and the next training job rejects {version} as "
                                       "abandoned") from exc
    return TrainResult(version, metrics, decision, losses, data.quarantined, [*data.warnings, *warnings])
