"""The uncertainty figures: accuracy vs copy-last-frame, calibration, out-of-distribution, fused scoring.

1. Collects (or reuses) a data directory: the pinned eval split (24 episodes,
   push policy, all shapes, ``workers.collect.create_eval_split``) and N train
   episodes (all shapes, push and random-waypoint policies, seeded).
2. ``uncertainty.train.train_candidate`` on it: h1/h5/h10 MSE, PSNR, SSIM of the
   ensemble mean next to copy-last-frame, Spearman(disagreement, error), time.
3. Out of distribution: a fresh ensemble trained on T-shape episodes only; mean
   disagreement on held-out T episodes against disk and L episodes (ratios).
4. ``uncertainty.benchmark.run_score_bench``: fused vs per-member loop frames/s.

Usage: .venv/bin/python bench/uncertainty_figures.py --data /tmp/figs [--train-episodes 80]
       [--epochs 4] [--members 5] [--threads 2] [--skip main,ood,bench] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from storage.catalog import Catalog
from storage.models import ModelRegistry
from uncertainty.benchmark import run_score_bench
from uncertainty.train import TrainConfig, fit, new_ensemble, train_candidate, train_windows
from workers.collect import collect_episode, create_eval_split
from workers.env import sample_state

SHAPES = ("T", "box", "L", "disk")


def collect(shapes, n: int, seed: int, steps: int, size: int):
    """n episodes cycling over ``shapes``; two thirds push policy, one third random waypoints."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        policy = "random_waypoints" if i % 3 == 2 else "push"
        start = sample_state(rng, shape=shapes[i % len(shapes)])
        out.append(collect_episode(start_state=start, policy=policy, seed=int(rng.integers(2**31)),
                                   steps=steps, image_size=size))
    return out


def prepare(data: Path, n_train: int, steps: int, size: int) -> Catalog:
    cat = Catalog(data)
    t0 = time.perf_counter()
    create_eval_split(cat, episodes=24, seed=1234, steps=steps, image_size=size)
    have = cat.count(split="train")
    if have < n_train:
        for ep in collect(SHAPES, n_train - have, seed=100 + have, steps=steps, size=size):
            cat.add_episode(ep)
    print(f"data: {cat.count(split='train')} train / {cat.count(split='eval')} eval episodes "
          f"({time.perf_counter() - t0:.1f}s to collect)", file=sys.stderr)
    return cat


def main_figure(cat: Catalog, data: Path, args) -> dict:
    cfg = TrainConfig(members=args.members, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                      seed=args.seed, device="cpu", max_episodes=args.train_episodes, progress=True)
    t0 = time.perf_counter()
    result = train_candidate(cat, ModelRegistry(data), cfg)
    m = result.metrics
    keys = ["train_episodes", "train_windows", "epochs", "train_seconds", "eval_episodes", "eval_windows",
            "spearman", "sparsification_error"]
    for h in (1, 5, 10):
        keys += [f"h{h}_mse", f"h{h}_psnr", f"h{h}_ssim", f"baseline_h{h}_mse", f"baseline_h{h}_psnr",
                 f"baseline_h{h}_ssim", f"h{h}_psnr_gain_db"]
    out = {k: m.get(k) for k in keys}
    out.update(version=result.version, promoted=result.decision.promoted, members=args.members,
               batch_size=args.batch_size, total_seconds=round(time.perf_counter() - t0, 1),
               losses=result.losses, sparsification=m["sparsification"])
    return out


def ood_figure(args) -> dict:
    t0 = time.perf_counter()
    train = collect(("T",), args.ood_train_episodes, seed=5000, steps=args.steps, size=args.image_size)
    groups = {shape: collect((shape,), args.ood_test_episodes, seed=6000 + i, steps=args.steps,
                             size=args.image_size)
              for i, shape in enumerate(SHAPES)}
    cfg = TrainConfig(members=args.members, epochs=args.ood_epochs, batch_size=args.batch_size, lr=args.lr,
                      seed=args.seed, device="cpu", progress=True)
    ens = new_ensemble(cfg, train)
    fit(ens, train_windows(train, ens, cfg), cfg)
    scores = {s: [(ens.disagreement(e.frames, e.actions), e.states[:, -1] > 0.5) for e in eps]
              for s, eps in groups.items()}
    # Disagreement grows with how many pixels move (the T is the largest shape), so also report it
    # per unit of actual change: summed disagreement over summed copy-last-frame error.
    change = {s: [np.append(np.mean((e.frames[1:].astype(np.float64) - e.frames[:-1]) ** 2 / 255 ** 2,
                                    axis=(1, 2, 3)), np.nan) for e in eps] for s, eps in groups.items()}
    per_change = {}
    for s in SHAPES:
        d = np.concatenate([d for d, _ in scores[s]])
        c = np.concatenate(change[s])
        ok = np.isfinite(d) & np.isfinite(c)
        per_change[s] = float(d[ok].sum() / c[ok].sum())
    mean = {s: float(np.mean([np.nanmean(d) for d, _ in v])) for s, v in scores.items()}
    # Where the pusher touches the object the object's shape matters most.
    contact = {s: float(np.nanmean(np.concatenate([d[c] for d, c in v]))) for s, v in scores.items()}
    return {"train": f"{len(train)} T episodes", "epochs": args.ood_epochs,
            "test_episodes_per_shape": args.ood_test_episodes,
            "mean_disagreement": mean,
            "ratio_to_heldout_T": {s: mean[s] / mean["T"] for s in SHAPES if s != "T"},
            "mean_disagreement_in_contact": contact,
            "contact_ratio_to_heldout_T": {s: contact[s] / contact["T"] for s in SHAPES if s != "T"},
            "disagreement_per_unit_change": per_change,
            "per_change_ratio_to_heldout_T": {s: per_change[s] / per_change["T"] for s in SHAPES if s != "T"},
            "seconds": round(time.perf_counter() - t0, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--train-episodes", type=int, default=80)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--image-size", type=int, default=64)
    p.add_argument("--members", type=int, default=5)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=1.5e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--ood-train-episodes", type=int, default=30)
    p.add_argument("--ood-epochs", type=int, default=3)
    p.add_argument("--ood-test-episodes", type=int, default=8)
    p.add_argument("--bench-seconds", type=float, default=20.0)
    p.add_argument("--skip", default="", help="comma list of main, ood, bench")
    p.add_argument("--json", type=Path, help="also write the figures here")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    skip = set(filter(None, args.skip.split(",")))
    figures: dict = {"threads": args.threads}
    if "main" not in skip:
        figures["main"] = main_figure(prepare(args.data, args.train_episodes, args.steps, args.image_size),
                                      args.data, args)
        print(json.dumps(figures["main"], indent=1, default=str), file=sys.stderr)
    if "ood" not in skip:
        figures["ood"] = ood_figure(args)
        print(json.dumps(figures["ood"], indent=1), file=sys.stderr)
    if "bench" not in skip:
        figures["bench"] = {f"batch{b}": run_score_bench(members=5, image_size=64, batch=b, threads=args.threads,
                                                         seconds=args.bench_seconds / 2, rounds=5)
                            for b in (48, 1)}
    text = json.dumps(figures, indent=1, default=str)
    print(text)
    if args.json:
        args.json.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
