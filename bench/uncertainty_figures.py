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
(``--help`` for every flag.) Every flag is checked before anything is collected or trained, exit 2 in one line:
its value, and the flags against each other -- a flag of a figure ``--skip`` leaves out, ``--steps`` too short
for ``--context`` or ``--ood-horizon``, an ``--ood-cache`` made with other flags than those given, a
``--json`` or ``--ood-cache`` that could not be written at the end; ``--data`` is needed unless ``--skip main``.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import torch

from orchestrator.cli.common import (Parser, data_dir, ensemble_size, epoch_count, episode_steps, non_negative_int,
                                     positive_float, positive_int, torch_device, trainable_image_size)
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.records import TRAINABLE_SIZES
from uncertainty.benchmark import run_score_bench
from uncertainty import metrics as M
from uncertainty.checkpoint import load_ensemble
from uncertainty.data import build_windows, load_eval
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig
from uncertainty.train import TrainConfig, fit, new_ensemble, resolve_device, train_candidate, train_windows
from workers.collect import EvalSplitConflict, collect_episode, create_eval_split
from workers.env import SHAPE_PALETTE, sample_state

SHAPES = ("T", "box", "L", "disk")

#: How many steps ``calibration_variants`` rolls out after the context frames (the eval episodes need as many).
CALIBRATION_HORIZON = 5

#: The OOD ensemble's context frames (``TrainConfig``'s default).
OOD_CONTEXT = TrainConfig.context


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
def calibration_variants(ens, cat: Catalog, horizon: int = CALIBRATION_HORIZON) -> dict:
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
                      lr=args.ood_lr, seed=args.seed, device=args.device, bootstrap=args.ood_bootstrap, progress=True,
                      context=OOD_CONTEXT)
    ens = new_ensemble(cfg, train)
    losses: list[float] = []
    if args.ood_cache is not None and args.ood_cache.exists():
        state = torch.load(args.ood_cache, map_location="cpu", weights_only=True)
        ens.load_state_dict(state["weights"])  # (onto the ensemble's device)
        losses = state["losses"]
    else:
        losses = fit(ens, train_windows(train, ens, cfg), cfg)
        if args.ood_cache is not None:
            torch.save({"weights": ens.state_dict(), "losses": losses, "flags": ood_flags(args)}, args.ood_cache)
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


#: The figures ``--skip`` can leave out, in the order they are made.
FIGURES = ("main", "ood", "bench")

#: The flags that set one figure (or two) only: given with every figure they set skipped, they contradict --skip.
#: (Not --data: the recorded commands of BENCHMARKS.md pass it to every figure; it is unused without the main one.)
FIGURE_OF = {"train_episodes": {"main"}, "image_size": {"main"}, "epochs": {"main"},
             "batch_size": {"main"}, "lr": {"main"}, "context": {"main"}, "bootstrap": {"main"},
             "variance_head": {"main"}, "steps": {"main", "ood"}, "members": {"main", "ood"},
             "seed": {"main", "ood"}, "palette": {"main", "ood"},
             **{dest: {"ood"} for dest in ("ood_train_episodes", "ood_epochs", "ood_test_episodes", "ood_image_size",
                                          "ood_batch_size", "ood_lr", "ood_bootstrap", "ood_random_physics",
                                          "ood_horizon", "ood_cache")},
             "bench_seconds": {"bench"}, "bench_threads": {"bench"}}


def _skip(text: str) -> frozenset[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in FIGURES]
    if unknown:
        raise argparse.ArgumentTypeError(f"expected a comma list of {', '.join(FIGURES)}, found {unknown[0]!r}")
    return frozenset(names)


def _thread_counts(text: str) -> list[int]:
    try:
        return [positive_int(t) for t in text.split(",")]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a comma list of positive integers such as 1,2, "
                                         f"found {text!r}") from None


def _output_file(text: str) -> Path:
    """A file to write at the end of a long run: refused now if it cannot be written then."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"expected a file, found a directory at {path}")
    if not path.parent.is_dir():
        raise argparse.ArgumentTypeError(f"expected a file in an existing directory, found no directory "
                                         f"{path.parent}")
    return path


def build_parser() -> Parser:
    """The command line; every value is checked as it is parsed, the flags against each other by ``check_args``."""
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=data_dir, metavar="DIR",
                   help="main figure: data directory of the eval split and the train episodes, collected into if "
                        "short of --train-episodes (required unless --skip main; unused then)")
    p.add_argument("--train-episodes", type=positive_int, default=80, help="main figure: train episodes (default 80)")
    p.add_argument("--steps", type=episode_steps, default=50,
                   help="steps of every episode collected, main and OOD (default 50)")
    p.add_argument("--image-size", type=trainable_image_size, default=64,
                   help=f"main figure: frame size, {TRAINABLE_SIZES} (default 64)")
    p.add_argument("--members", type=ensemble_size, default=5,
                   help="ensemble members of the main and OOD figures (default 5; the scoring bench always has 5)")
    p.add_argument("--epochs", type=epoch_count, default=4, help="main figure: training epochs (default 4)")
    p.add_argument("--batch-size", type=positive_int, default=16, help="main figure: training batch (default 16)")
    p.add_argument("--lr", type=positive_float, default=1.5e-3, help="main figure: learning rate (default 1.5e-3)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the members' training (default 0)")
    p.add_argument("--context", type=positive_int, default=2,
                   help=f"main figure: context frames per prediction (default 2; --steps at least this + "
                        f"{CALIBRATION_HORIZON})")
    p.add_argument("--bootstrap", action="store_true", help="main figure: members train on bootstrap resamples")
    p.add_argument("--variance-head", action="store_true",
                   help="main figure: members also predict their error variance (total-variance calibration)")
    p.add_argument("--palette", choices=("uniform", "per-shape"), default="uniform",
                   help="object colours: all alike (the service's world) or one per shape (workers.env.SHAPE_PALETTE);"
                        " (a data directory collected with the other one is refused: its eval split is pinned)")
    p.add_argument("--threads", type=positive_int, default=2, help="torch threads (default 2)")
    p.add_argument("--device", type=torch_device, default="cpu",
                   help="where the figures train and score: cpu (the default: the issue's figures are the CPU's), "
                        "cuda or auto")
    p.add_argument("--ood-train-episodes", type=positive_int, default=80,
                   help="OOD figure: T-shape episodes the OOD ensemble trains on (default 80)")
    p.add_argument("--ood-epochs", type=epoch_count, default=40, help="OOD figure: training epochs (default 40)")
    p.add_argument("--ood-test-episodes", type=positive_int, default=8,
                   help="OOD figure: held-out episodes per shape (default 8)")
    p.add_argument("--ood-image-size", type=trainable_image_size, default=32,
                   help=f"OOD figure: frame size, {TRAINABLE_SIZES} (default 32)")
    p.add_argument("--ood-batch-size", type=positive_int, default=32, help="OOD figure: training batch (default 32)")
    p.add_argument("--ood-lr", type=positive_float, default=2e-3, help="OOD figure: learning rate (default 2e-3)")
    p.add_argument("--ood-bootstrap", action="store_true", help="OOD figure: members train on bootstrap resamples")
    p.add_argument("--ood-random-physics", action="store_true", help="OOD figure: draw mass and frictions per episode")
    p.add_argument("--ood-horizon", type=positive_int, default=1,
                   help=f"OOD figure: disagreement horizon (default 1; at most --steps - {OOD_CONTEXT})")
    p.add_argument("--ood-cache", type=_output_file, metavar="FILE",
                   help="OOD figure: save the trained OOD ensemble here, with the flags it was trained with; "
                        "reuse it if present (one made with other flags is refused, naming them)")
    p.add_argument("--bench-seconds", type=positive_float, default=20.0,
                   help="scoring bench: seconds per thread count, split over batch 48 and batch 1 (default 20)")
    p.add_argument("--bench-threads", type=_thread_counts, metavar="N[,N...]",
                   help="scoring bench: comma list of torch thread counts (default --threads)")
    p.add_argument("--skip", type=_skip, default=frozenset(), metavar="FIGURE[,FIGURE...]",
                   help=f"leave these figures out, a comma list of {', '.join(FIGURES)} (not all three)")
    p.add_argument("--json", type=_output_file, metavar="FILE", help="also write the figures here")
    return p


def check_args(p: Parser, args: argparse.Namespace) -> None:
    """The flags against each other, before any work: exits 2 in one line (``p.error``) on the first conflict."""
    skip = args.skip
    if skip == set(FIGURES):
        p.error(f"--skip {','.join(FIGURES)} leaves no figure to make")
    for action in p._actions:
        figures = FIGURE_OF.get(action.dest)
        if figures and figures <= skip and getattr(args, action.dest) != p.get_default(action.dest):
            which = " and ".join(f for f in FIGURES if f in figures)
            p.error(f"{action.option_strings[0]} sets the {which} figure{'s' * (len(figures) > 1)}, which --skip "
                    f"leaves out")
    if "main" not in skip:
        if args.data is None:
            p.error("--data is required for the main figure (or --skip main)")
        if args.steps < args.context + CALIBRATION_HORIZON:
            p.error(f"--steps {args.steps} is too short for --context {args.context}: the main figure's calibration "
                    f"rolls out {CALIBRATION_HORIZON} steps after the context (--steps at least "
                    f"{args.context + CALIBRATION_HORIZON})")
    if "ood" not in skip:
        if args.ood_horizon > args.steps - OOD_CONTEXT:
            p.error(f"--ood-horizon {args.ood_horizon} leaves no step to score in episodes of --steps {args.steps} "
                    f"({OOD_CONTEXT} context frames first: at most {args.steps - OOD_CONTEXT})")
        if args.ood_cache is not None and args.ood_cache.exists():
            _check_ood_cache(p, args)
    if args.json is not None and args.ood_cache is not None and args.json.resolve() == args.ood_cache.resolve():
        p.error(f"--json and --ood-cache name the same file {args.json}")


def ood_flags(args: argparse.Namespace) -> dict:
    """The flags the OOD ensemble's training depends on, by name: an ``--ood-cache`` records them, and one made with
    others is refused (its members are convolutional: weights of any --ood-image-size load, and were reused)."""
    return {"--members": args.members, "--seed": args.seed, "--steps": args.steps, "--palette": args.palette,
            "--ood-train-episodes": args.ood_train_episodes, "--ood-epochs": args.ood_epochs,
            "--ood-image-size": args.ood_image_size, "--ood-batch-size": args.ood_batch_size, "--ood-lr": args.ood_lr,
            "--ood-bootstrap": args.ood_bootstrap, "--ood-random-physics": args.ood_random_physics}


def _check_ood_cache(p: Parser, args: argparse.Namespace) -> None:
    """A cache that cannot be read, holds an ensemble of other --members, or was made with other flags
    (``ood_flags``), is refused now, not after the main figure."""
    try:
        state = torch.load(args.ood_cache, map_location="cpu", weights_only=True)
    except OSError as exc:
        p.error(f"--ood-cache {args.ood_cache}: cannot read it ({exc.strerror})")
    except (RuntimeError, pickle.UnpicklingError, EOFError, ValueError):
        p.error(f"--ood-cache {args.ood_cache}: not a file torch.save wrote; give another file or remove it")
    if not (isinstance(state, dict) and isinstance(state.get("weights"), dict) and "losses" in state):
        p.error(f"--ood-cache {args.ood_cache}: not a saved OOD ensemble (no weights and losses in it)")
    weights = state["weights"]
    shape = PredictorConfig(image_size=args.ood_image_size, context=OOD_CONTEXT)
    try:
        Ensemble(shape, members=args.members).load_state_dict(weights)
    except RuntimeError:
        p.error(f"--ood-cache {args.ood_cache}: not the OOD ensemble of --members {args.members} (its weights "
                "differ in shape); give its --members, or another file")
    made = state.get("flags")
    if not isinstance(made, dict):
        p.error(f"--ood-cache {args.ood_cache}: it does not record the flags it was made with (written before "
                "they were recorded); give another file, or remove it to train again")
    other = [f"{flag} {made.get(flag)} (not {value})" for flag, value in ood_flags(args).items()
             if made.get(flag) != value]
    if other:
        p.error(f"--ood-cache {args.ood_cache}: made with {', '.join(other)}; give the flags it was made with, "
                "or another file, or remove it to train again")


def main(argv=None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    check_args(p, args)
    torch.set_num_threads(args.threads)
    skip = args.skip
    figures: dict = {"threads": args.threads, "device": args.device}
    if "main" not in skip:
        try:
            cat = prepare(args.data, args.train_episodes, args.steps, args.image_size, _palette(args))
        except EvalSplitConflict as exc:  # (raised before anything is collected)
            p.error(f"--data {args.data}: {exc}")
        figures["main"] = main_figure(cat, args.data, args)
        print(json.dumps(figures["main"], indent=1, default=str), file=sys.stderr)
    if "ood" not in skip:
        figures["ood"] = ood_figure(args)
        print(json.dumps(figures["ood"], indent=1), file=sys.stderr)
    if "bench" not in skip:
        # Several thread counts: with 2 threads on a busy 2-core machine every parallel region waits
        # for a descheduled thread, which hurts the loop (5x the regions) far more than the fused pass.
        threads = args.bench_threads or [args.threads]
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
