"""Scoring throughput: the fused ensemble against the per-member loop, in one run.

Both paths score the same windows with the same weights; frames/s counts
predicted next frames (windows) per second for the whole ensemble. The fused
path runs every member in one grouped convolution per layer; the loop runs the
members one after another. Timings are interleaved so machine load hits both.

Next to frames/s it reports the arithmetic rate of each path (GFLOP/s, from
``torch.utils.flop_counter``) and of one wide 3x3 convolution timed in the same
rounds (``CEILING_CONV``: 128 channels in and out, the shape convolution
libraries are fastest at): the practical fp32 ceiling for these layers on this
machine. Fusion removes per-call overhead, not arithmetic, so once a path runs
near that ceiling (large batches on a CPU) no fusion can make it much faster;
the share says how close each path is. (A square matrix product is not the
ceiling here: on AMD CPUs torch's MKL sgemm runs at under half the speed of
oneDNN's convolutions.)
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import torch
from torch.utils.flop_counter import FlopCounterMode

from uncertainty.ensemble import Ensemble
from uncertainty.errors import ConfigError
from uncertainty.model import PredictorConfig
from uncertainty.train import resolve_device


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


def _flops(fn, ctx, act) -> int:
    """Floating-point operations of one call (a multiply-add counts as 2)."""
    with FlopCounterMode(display=False) as counter:
        fn(ctx, act)
    return counter.get_total_flops()


CEILING_CONV = {"batch": 16, "channels": 128, "size": 32}
"""The convolution that measures the arithmetic ceiling: (batch, channels, size, size) in, 3x3, same channels out."""


def _ceiling_conv(dev: torch.device, gen: torch.Generator):
    """(fn(x, w), x, w, flops per call) of the ceiling convolution, channels-last like the fused pass."""
    b, c, s = CEILING_CONV["batch"], CEILING_CONV["channels"], CEILING_CONV["size"]
    x = torch.rand(b, c, s, s, generator=gen).to(dev).contiguous(memory_format=torch.channels_last)
    w = torch.rand(c, c, 3, 3, generator=gen).to(dev)
    return (lambda x, w: torch.nn.functional.conv2d(x, w, padding=1)), x, w, 2 * b * c * c * 9 * s * s


def run_score_bench(members: int = 5, image_size: int = 64, seconds: float = 10.0, batch: int = 48,
                    threads: int | None = None, device: str = "auto", include_vmap: bool = True,
                    rounds: int = 3, seed: int = 0) -> dict:
    """Frames/s of the fused ensemble and of the per-member loop (and vmap), measured in one run.

    Returns a JSON-able dict: config, device, fused_fps, loop_fps, speedup (fused / loop),
    vmap_fps, max_abs_diff (fused vs loop), per-round figures, and the arithmetic:
    gflop_per_frame, <path>_gflops,
    ceiling_gflops (a wide convolution's, measured in the same rounds) and <path>_share_of_ceiling
    (a path's GFLOP/s over the ceiling's). Raises ``ConfigError`` for a bad setting, cuda without CUDA
    included.
    """
    cfg = ScoreBenchConfig(members, image_size, batch, seconds, threads, device, include_vmap, seed)
    dev = resolve_device(device)  # ConfigError, not torch's assertion, when cuda is asked for without CUDA
    if threads is not None:
        torch.set_num_threads(threads)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    ens = Ensemble(PredictorConfig(image_size=image_size), members=members, seed=seed).to(dev).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():  # a fresh output layer is scaled down: make every layer matter to max_abs_diff
        for p in ens.params:
            p.add_(0.05 * torch.randn(p.shape, generator=gen).to(dev))
    ctx = torch.rand(batch, ens.config.context, 3, image_size, image_size, generator=gen).to(dev)  # (B,C,3,H,W)
    act = torch.randn(batch, ens.config.action_dim, generator=gen).to(dev)                         # (B, A)
    paths = {"fused": ens.forward, "loop": ens.forward_loop}
    if include_vmap:
        paths["vmap"] = ens.forward_vmap
    ceiling, cx, cw, ceiling_flops = _ceiling_conv(dev, gen)
    budget = seconds / (rounds * (len(paths) + 1))
    per_round = []
    with torch.inference_mode():
        diff = float((ens.forward(ctx, act) - ens.forward_loop(ctx, act)).abs().max())
        flops = {name: _flops(fn, ctx, act) for name, fn in paths.items()}
        for fn in paths.values():  # warm-up: oneDNN primitive creation, allocator
            fn(ctx, act)
        ceiling(cx, cw)
        for _ in range(rounds):
            row = {}
            for name, fn in paths.items():
                calls, elapsed = _time(fn, ctx, act, budget, sync)
                row[f"{name}_fps"] = calls * batch / elapsed
            calls, elapsed = _time(ceiling, cx, cw, budget, sync)
            row["ceiling_gflops"] = calls * ceiling_flops / elapsed / 1e9
            per_round.append(row)
    out = {"config": asdict(cfg), "device": str(dev), "threads": torch.get_num_threads(),
           "max_abs_diff": diff, "rounds": per_round, "gflop_per_frame": flops["loop"] / batch / 1e9,
           "ceiling_gflops": max(r["ceiling_gflops"] for r in per_round)}
    for name in paths:
        out[f"{name}_fps"] = max(r[f"{name}_fps"] for r in per_round)
        out[f"{name}_gflops"] = out[f"{name}_fps"] * flops[name] / batch / 1e9
        out[f"{name}_share_of_ceiling"] = out[f"{name}_gflops"] / out["ceiling_gflops"]
    out["speedup"] = out["fused_fps"] / out["loop_fps"]
    out["speedup_per_round"] = [r["fused_fps"] / r["loop_fps"] for r in per_round]
    return out
