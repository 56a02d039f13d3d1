"""The uncertainty figures: accuracy vs copy-last-frame, calibration, out-of-distribution, fused scoring.

1. Collects (or reuses) a data directory: the pinned eval split (24 episodes,
   push policy, all shapes, ``workers.collect.create_eval_split``) and N train
   episodes (all shapes, push and random-waypoint policies, seeded).
2. ``uncertainty.train.train_candidate`` on it: h1/h5/h10 MSE, PSNR, SSIM of the
   ensemble mean next to copy-last-frame, Spearman(disagreement, error), time;
   plus ``calibration_variants`` (the same Spearman per other sample definitions).
3. Out of distribution: a fresh ensemble trained on T-shape episodes only; mean
   disagreement on held-out T episodes against box, L and disk episodes collected
   with the same policies and steps (ratios), next to the model's own error there
   and a few normalised variants of the disagreement (see ``ood_scores``).
4. ``uncertainty.benchmark.run_score_bench``: fused vs per-member loop frames/s,
   batch 48 and batch 1.

Usage: .venv/bin/python bench/uncertainty_figures.py --data /tmp/figs [--train-episodes 80]
       [--epochs 4] [--bootstrap] [--image-size 64] [--members 5] [--threads 2] [--device cpu]
       [--ood-train-episodes 80 --ood-epochs 40 --ood-image-size 32 --ood-cache oodL.pt]
       [--skip main,ood,bench] [--json out.json]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from orchestrator.cli.common import Parser, torch_device, trainable_image_size
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.records import TRAINABLE_SIZES
from uncertainty.benchmark import run_score_bench
from uncertainty import metrics as M
from uncertainty.checkpoint import load_ensemble
from uncertainty.data import build_windows, load_eval
from uncertainty.train import TrainConfig, fit, new_ensemble, resolve_device, train_candidate, train_windows
from workers.collect import collect_episode, create_eval_split
from workers.env import SHAPE_PALETTE, sample_state

SHAPES = ("T", "box", "L", "disk")


def collect(shapes, n: int, seed: int, steps: int, size: int, random_physics: bool = False, palette=None):
    """n episodes cycling over ``shapes``; two thirds push policy, one third random waypoints."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        policy = "random_waypoints" if i % 3 == 2 else "push"
        start = sample_state(rng, shape=shapes[i % len(shapes)], random_physics=random_physics)
        out.append(collect_episode(start_state=start, policy=policy, seed=int(rng.integers(2**31)),
                                   steps=steps, image_size=size, palette=palette))
    return out


def prepare(data: Path, n_train: int, steps: int, size: int, palette=None) -> Catalog:
    cat = Catalog(data)
    t0 = time.perf_counter()
    create_eval_split(cat, episodes=24, seed=1234, steps=steps, image_size=size, palette=palette)
    have = cat.count(split="train")
    if have < n_train:
        for ep in collect(SHAPES, n_train - have, seed=100 + have, steps=steps, size=size, palette=palette):
            cat.add_episode(ep)
    print(f"data: {cat.count(split='train')} train / {cat.count(split='eval')} eval episodes "
          f"({time.perf_counter() - t0:.1f}s to collect)", file=sys.stderr)
    return cat


def main_figure(cat: Catalog, data: Path, args) -> dict:
    cfg = TrainConfig(members=args.members, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                      seed=args.seed, device=args.device, max_episodes=args.train_episodes, progress=True,
                      bootstrap=args.bootstrap, variance_head=args.variance_head, context=args.context)
    t0 = time.perf_counter()
    registry = ModelRegistry(data)
    result = train_candidate(cat, registry, cfg)
    m = result.metrics
    keys = ["train_episodes", "train_windows", "epochs", "train_seconds", "eval_episodes", "eval_windows",
            "spearman", "sparsification_error", "spearman_total", "spearman_predicted_variance",
            "sparsification_error_total", "h1_total_variance_ratio", "h1_predicted_variance"]
    for h in (1, 5, 10):
        keys += [f"h{h}_mse", f"h{h}_psnr", f"h{h}_ssim", f"baseline_h{h}_mse", f"baseline_h{h}_psnr",
                 f"baseline_h{h}_ssim", f"h{h}_psnr_gain_db"]
    out = {k: m.get(k) for k in keys}
    out.update(version=result.version, promoted=result.decision.promoted, members=args.members,
               batch_size=args.batch_size, total_seconds=round(time.perf_counter() - t0, 1),
               losses=result.losses, sparsification=m["sparsification"], bootstrap=args.bootstrap,
               image_size=args.image_size, variance_head=args.variance_head, palette=args.palette,
               context=args.context)
    ens = load_ensemble(registry, result.version, resolve_device(args.device))
    out["calibration_variants"] = calibration_variants(ens, cat)
    return out


@torch.inference_mode()
def calibration_variants(ens, cat: Catalog, horizon: int = 5) -> dict:
    """Spearman(disagreement, error of the ensemble mean) on the eval split, per sample definition.

    per_window_h1 is the figure ``evaluate`` reports (one sample per window, next frame);
    per_window_h{n}: disagreement and error at rollout step n of the same windows;
    per_window_mean_h1..n: both averaged over the first n rollout steps;
    per_episode_h1: both averaged over each eval episode's windows (24 samples);
    within_episode_h1: the mean over episodes of the per-window Spearman inside one episode.
    """
    episodes, _ = load_eval(cat)
    w = build_windows(episodes, ens.config, horizon=horizon)
    var, err = [], []
    for lo in range(0, len(w), 128):
        ctx, act, tgt = w.batch(torch.arange(lo, min(lo + 128, len(w))), ens.device)
        preds = ens.rollout(ctx, ens.normalize_actions(act))               # (K, B, H, 3, H, W)
        var.append(preds.var(dim=0, unbiased=False).mean(dim=(2, 3, 4)))  # (B, H)
        err.append((preds.mean(dim=0) - tgt).pow(2).mean(dim=(2, 3, 4)))  # (B, H)
    v, e = torch.cat(var).double().cpu().numpy(), torch.cat(err).double().cpu().numpy()  # (N, H)
    ep = w.episode
    out = {"windows": len(w), "per_window_h1": M.spearman(v[:, 0], e[:, 0]),
           f"per_window_h{horizon}": M.spearman(v[:, -1], e[:, -1]),
           f"per_window_mean_h1..{horizon}": M.spearman(v.mean(1), e.mean(1)),
           "per_episode_h1": M.spearman([v[ep == i, 0].mean() for i in range(len(episodes))],
                                        [e[ep == i, 0].mean() for i in range(len(episodes))]),
           "within_episode_h1": float(np.nanmean([M.spearman(v[ep == i, 0], e[ep == i, 0])
                                                  for i in range(len(episodes))])),
           "pearson_per_window_h1": float(np.corrcoef(v[:, 0], e[:, 0])[0, 1])}
    return out


def _frame_change(ep) -> np.ndarray:
    """(T,) mean squared change from frame t to t+1 in [0,1] units (NaN at the last step)."""
    f = ep.frames.astype(np.float64) / 255.0
    return np.append(np.mean((f[1:] - f[:-1]) ** 2, axis=(1, 2, 3)), np.nan)


def _palette(args):
    return SHAPE_PALETTE if args.palette == "per-shape" else None


def ood_figure(args) -> dict:
    """Disagreement of a T-only ensemble on held-out T against box, L and disk (same policies and steps)."""
    t0 = time.perf_counter()
    size = args.ood_image_size
    palette = _palette(args)
    train = collect(("T",), args.ood_train_episodes, seed=5000, steps=args.steps, size=size,
                    random_physics=args.ood_random_physics, palette=palette)
    groups = {shape: collect((shape,), args.ood_test_episodes, seed=6000 + i, steps=args.steps, size=size,
                             random_physics=args.ood_random_physics, palette=palette)
              for i, shape in enumerate(SHAPES)}
    cfg = TrainConfig(members=args.members, epochs=args.ood_epochs, batch_size=args.ood_batch_size,
                      lr=args.ood_lr, seed=args.seed, device=args.device, bootstrap=args.ood_bootstrap, progress=True)
    ens = new_ensemble(cfg, train)
    losses: list[float] = []
    if args.ood_cache is not None and args.ood_cache.exists():
        state = torch.load(args.ood_cache, map_location="cpu", weights_only=True)
        ens.load_state_dict(state["weights"])  # (onto the ensemble's device)
        losses = state["losses"]
    else:
        losses = fit(ens, train_windows(train, ens, cfg), cfg)
        if args.ood_cache is not None:
            torch.save({"weights": ens.state_dict(), "losses": losses}, args.ood_cache)
    train_s = time.perf_counter() - t0
    # Training episodes too: how far members agree where they have seen the data (convergence).
    groups["T_train"] = train[:args.ood_test_episodes]
    per_shape = {s: ood_scores(ens, eps, args.ood_horizon) for s, eps in groups.items()}
    out = {"train": f"{len(train)} T episodes", "image_size": size, "epochs": args.ood_epochs,
           "batch_size": args.ood_batch_size, "lr": args.ood_lr, "bootstrap": args.ood_bootstrap,
           "random_physics": args.ood_random_physics, "palette": args.palette, "train_losses": losses,
           "test_episodes_per_shape": args.ood_test_episodes, "steps": args.steps, "horizon": args.ood_horizon}
    for key in next(iter(per_shape.values())):
        out[key] = {s: per_shape[s][key] for s in per_shape}
        if key.startswith("disagreement") or key.startswith("error"):
            base = per_shape["T"][key]  # 0 when held-out T has no such steps (e.g. no contact): no ratio
            out[key + "_ratio_to_heldout_T"] = {s: per_shape[s][key] / base if base else None
                                                for s in per_shape if s != "T"}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    out["train_seconds"] = round(train_s, 1)
    return out


@torch.inference_mode()
def ood_scores(ens, episodes, horizon: int = 1) -> dict:
    """Mean per-step figures over ``episodes`` (every step pooled; NaN steps dropped).

    disagreement: the plain score (variance across members of the predicted next frame, mean over
    pixels; with ``horizon`` > 1 also over each member's own rollout of that many steps);
    disagreement_contact: the same over steps where the pusher touches the object;
    disagreement_per_change: summed disagreement over summed true frame change (how much moves);
    disagreement_moving: variance averaged over the pixels the ensemble mean predicts to change
    (|mean - last| > 2/255), i.e. the same variance normalised by the predicted moving area;
    disagreement_per_predicted_change: summed disagreement over the summed squared change the
    ensemble mean predicts (|mean - last|^2): needs no true next frame;
    error: the ensemble mean's MSE; error_copy_last: copy-last-frame MSE.
    """
    d, dc, chg, mov, err, pchg = [], [], [], [], [], []
    for ep in episodes:
        score = ens.disagreement(ep.frames, ep.actions, horizon=horizon)
        d.append(score)
        dc.append(score[ep.states[:, -1] > 0.5])
        chg.append(_frame_change(ep))
        m, e, pc = _moving_variance(ens, ep)
        mov.append(m)
        err.append(e)
        pchg.append(pc)
    d_all, c_all = np.concatenate(d), np.concatenate(chg)
    ok = np.isfinite(d_all) & np.isfinite(c_all)
    return {"disagreement": float(np.nanmean(d_all)),
            "disagreement_contact": float(np.nanmean(np.concatenate(dc))),
            "disagreement_per_change": float(d_all[ok].sum() / c_all[ok].sum()),
            "disagreement_moving": float(np.nanmean(np.concatenate(mov))),
            "disagreement_per_predicted_change": float(np.nansum(d_all) / np.concatenate(pchg).sum()),
            "error": float(np.nanmean(np.concatenate(err))),
            "error_copy_last": float(np.nanmean(c_all)),
            "contact_fraction": float(np.mean(np.concatenate([ep.states[:, -1] > 0.5 for ep in episodes])))}


def _moving_variance(ens, ep) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window: member variance over the pixels the mean predicts to move, the mean's MSE, and the
    mean squared change the mean predicts."""
    w = build_windows([ep], ens.config, horizon=1)
    ctx, act, tgt = w.batch(torch.arange(len(w)), ens.device)         # (B,C,3,H,W), (B,1,A), (B,1,3,H,W)
    preds = ens(ctx, ens.normalize_actions(act[:, 0])).clamp(0, 1)     # (K, B, 3, H, W)
    mean = preds.mean(dim=0)                                           # (B, 3, H, W)
    var = preds.var(dim=0, unbiased=False).mean(dim=1)                 # (B, H, W)
    moving = ((mean - ctx[:, -1]).abs().amax(dim=1) > 2 / 255).float()  # (B, H, W)
    mv = (var * moving).sum(dim=(1, 2)) / moving.sum(dim=(1, 2)).clamp(min=1)
    e = (mean - tgt[:, 0]).pow(2).mean(dim=(1, 2, 3))
    pc = (mean - ctx[:, -1]).pow(2).mean(dim=(1, 2, 3))
    return mv.double().cpu().numpy(), e.double().cpu().numpy(), pc.double().cpu().numpy()


def main(argv=None) -> int:
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--train-episodes", type=int, default=80)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--image-size", type=trainable_image_size, default=64, help=f"frame size, {TRAINABLE_SIZES}")
    p.add_argument("--members", type=int, default=5)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=1.5e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--context", type=int, default=2, help="main figure: context frames per prediction")
    p.add_argument("--bootstrap", action="store_true", help="main figure: members train on bootstrap resamples")
    p.add_argument("--variance-head", action="store_true",
                   help="main figure: members also predict their error variance (total-variance calibration)")
    p.add_argument("--palette", choices=("uniform", "per-shape"), default="uniform",
                   help="object colours: all alike (the service's world) or one per shape (workers.env.SHAPE_PALETTE);"
                        " (a data directory collected with the other one is refused: its eval split is pinned)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", type=torch_device, default="cpu",
                   help="where the figures train and score: cpu (the default: the issue's figures are the CPU's), "
                        "cuda or auto")
    p.add_argument("--ood-train-episodes", type=int, default=80)
    p.add_argument("--ood-epochs", type=int, default=40)
    p.add_argument("--ood-test-episodes", type=int, default=8)
    p.add_argument("--ood-image-size", type=trainable_image_size, default=32, help="frame size of the OOD check")
    p.add_argument("--ood-batch-size", type=int, default=32)
    p.add_argument("--ood-lr", type=float, default=2e-3)
    p.add_argument("--ood-bootstrap", action="store_true", help="members train on bootstrap resamples")
    p.add_argument("--ood-random-physics", action="store_true", help="draw mass and frictions per episode")
    p.add_argument("--ood-horizon", type=int, default=1, help="disagreement horizon of the OOD check")
    p.add_argument("--ood-cache", type=Path,
                   help="save the trained OOD ensemble here; reuse it if present (pass the same OOD flags)")
    p.add_argument("--bench-seconds", type=float, default=20.0)
    p.add_argument("--bench-threads", default="", help="comma list of torch thread counts (default --threads)")
    p.add_argument("--skip", default="", help="comma list of main, ood, bench")
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    skip = set(filter(None, args.skip.split(",")))
    figures: dict = {"threads": args.threads, "device": args.device}
    if "main" not in skip:
        cat = prepare(args.data, args.train_episodes, args.steps, args.image_size, _palette(args))
        figures["main"] = main_figure(cat, args.data, args)
        print(json.dumps(figures["main"], indent=1, default=str), file=sys.stderr)
    if "ood" not in skip:
        figures["ood"] = ood_figure(args)
        print(json.dumps(figures["ood"], indent=1), file=sys.stderr)
    if "bench" not in skip:
        # Several thread counts: with 2 threads on a busy 2-core machine every parallel region waits
        # for a descheduled thread, which hurts the loop (5x the regions) far more than the fused pass.
        threads = [int(t) for t in args.bench_threads.split(",")] if args.bench_threads else [args.threads]
        figures["bench"] = {f"threads{t}_batch{b}": run_score_bench(members=5, image_size=64, batch=b, threads=t,
                                                                   seconds=args.bench_seconds / 2, rounds=5,
                                                                   device=args.device)
                            for t in threads for b in (48, 1)}
        torch.set_num_threads(args.threads)
    text = json.dumps(figures, indent=1, default=str)
    print(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
