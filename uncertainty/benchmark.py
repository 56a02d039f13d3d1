"""Scoring throughput: the fused ensemble against the per-member loop, in one run.

Both paths score the same windows with the same weights; frames/s counts
predicted next frames (windows) per second for the whole ensemble. The fused
path runs every member in one grouped convolution per layer; the loop runs the
members one after another. Timings are interleaved so machine load hits both.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import torch

from uncertainty.ensemble import Ensemble, default_device
from uncertainty.errors import ConfigError
from uncertainty.model import PredictorConfig


@dataclass
class ScoreBenchConfig:
    """What ``run_score_bench`` measures."""

    members: int = 5
    """Ensemble size K."""
    image_size: int = 64
    """Frame size."""
    batch: int = 48
    """Windows per forward (48 = one 50-step episode with context 2)."""
    seconds: float = 10.0
    """Rough total measuring time, split across the paths and rounds."""
    threads: int | None = None
    """torch intra-op threads (None leaves torch's default)."""
    device: str = "auto"
    """"auto", "cpu" or "cuda"."""
    include_vmap: bool = True
    """Also time the torch.vmap fusion."""
    seed: int = 0
    """Seeds weights and inputs."""

    def __post_init__(self) -> None:
        if self.members < 1 or self.batch < 1 or not self.seconds > 0:
            raise ConfigError(f"members, batch and seconds must be positive, found "
                              f"{self.members}, {self.batch}, {self.seconds}")


def _time(fn, ctx, act, budget: float, sync) -> tuple[int, float]:
    calls, start = 0, time.perf_counter()
    while True:
        fn(ctx, act)
        sync()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= budget:
            return calls, elapsed


def run_score_bench(members: int = 5, image_size: int = 64, seconds: float = 10.0, batch: int = 48,
                    threads: int | None = None, device: str = "auto", include_vmap: bool = True,
                    rounds: int = 3, seed: int = 0) -> dict:
    """Frames/s of the fused ensemble and of the per-member loop (and vmap), measured in one run.

    Returns a JSON-able dict: config, device, fused_fps, loop_fps, speedup (fused / loop),
    vmap_fps, max_abs_diff (fused vs loop) and per-round figures.
    """
    cfg = ScoreBenchConfig(members, image_size, batch, seconds, threads, device, include_vmap, seed)
    if threads is not None:
        torch.set_num_threads(threads)
    dev = default_device() if device == "auto" else torch.device(device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    ens = Ensemble(PredictorConfig(image_size=image_size), members=members, seed=seed).to(dev).eval()
    gen = torch.Generator().manual_seed(seed)
    ctx = torch.rand(batch, ens.config.context, 3, image_size, image_size, generator=gen).to(dev)  # (B,C,3,H,W)
    act = torch.randn(batch, ens.config.action_dim, generator=gen).to(dev)                         # (B, A)
    paths = {"fused": ens.forward, "loop": ens.forward_loop}
    if include_vmap:
        paths["vmap"] = ens.forward_vmap
    budget = seconds / (rounds * len(paths))
    per_round = []
    with torch.inference_mode():
        diff = float((ens.forward(ctx, act) - ens.forward_loop(ctx, act)).abs().max())
        for fn in paths.values():  # warm-up: oneDNN primitive creation, allocator
            fn(ctx, act)
        for _ in range(rounds):
            row = {}
            for name, fn in paths.items():
                calls, elapsed = _time(fn, ctx, act, budget, sync)
                row[f"{name}_fps"] = calls * batch / elapsed
            per_round.append(row)
    out = {"config": asdict(cfg), "device": str(dev), "threads": torch.get_num_threads(),
           "max_abs_diff": diff, "rounds": per_round}
    for name in paths:
        out[f"{name}_fps"] = max(r[f"{name}_fps"] for r in per_round)
    out["speedup"] = out["fused_fps"] / out["loop_fps"]
    out["speedup_per_round"] = [r["fused_fps"] / r["loop_fps"] for r in per_round]
    return out
