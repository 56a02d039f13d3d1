"""Training settings: ``TrainConfig``, the one configuration of a training run.

Free of torch, so the CLI can build its parsers (whose defaults come from here)
without loading the models; ``uncertainty.train`` turns ``device`` into a torch device.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from uncertainty.errors import ConfigError


#: Most members an ensemble may have, and the widest channel count of a fresh model: beyond them a typo (``--members
#: 500``, ``--widths 16,32,6400``) would allocate gigabytes, or run for days, before anything says so.
MAX_MEMBERS = 64
MAX_WIDTH = 1024
#: Most passes over the training windows: ``--epochs 10**20`` trained until Ctrl-C. The README's longest runs train
#: 30; a cap far above them stops only a typo's extra zeros.
MAX_EPOCHS = 10_000
#: Largest seed: torch's generators take 64 bits, and a larger ``--seed`` failed deep in the trainer.
MAX_SEED = 2**64 - 1


@dataclass
class TrainConfig:
    """One training run (``activecollect train`` builds it)."""

    members: int = 5
    """Ensemble size K (ignored when warm-starting: the champion's K is kept)."""
    epochs: int = 8
    """Passes over the training windows."""
    batch_size: int = 16
    """Windows per member per step."""
    lr: float = 1.5e-3
    """Peak Adam learning rate (cosine-decayed to a tenth)."""
    grad_clip: float | None = 1.0
    """Per-member gradient norm cap (None: no clipping); keeps one bad batch from derailing a member."""
    bootstrap: bool = False
    """Train each member on a bootstrap resample of the episodes."""
    seed: int = 0
    """Seeds initialisation, shuffling and bootstrap draws."""
    device: str = "auto"
    """"auto" (CUDA if available), "cpu" or "cuda"."""
    max_windows: int | None = None
    """Cap on training windows (a seeded random subset); None uses all."""
    max_episodes: int | None = None
    """Cap on training episodes (the snapshot's first ones); None uses all."""
    from_champion: bool = False
    """Warm-start from the champion's weights (and keep its normalisation)."""
    context: int = 2
    """Context frames C of a fresh model."""
    widths: tuple[int, int, int] = (16, 32, 64)
    """Channel widths of a fresh model."""
    variance_head: bool = False
    """A fresh model's members also predict a per-pixel variance of their error (beta-NLL);
    ``eval`` then reports the calibration of the total predictive variance too."""
    min_rel_improvement: float = 0.02
    """The gate's minimum relative improvement of h1_mse over the champion."""
    eval_rollout_stride: int = 5
    """Start every n-th eval step for the h5/h10 rollouts (h1 uses every step)."""
    progress: bool | None = None
    """Show a progress bar; None: only when stderr is a terminal."""

    def __post_init__(self) -> None:
        for name in ("members", "epochs", "batch_size", "context", "eval_rollout_stride"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"{name} must be >= 1, found {getattr(self, name)}")
        if self.members < 2:  # its disagreement is 0 everywhere: nothing for the planner, nan for calibration
            raise ConfigError(f"members must be >= 2 (one member cannot disagree), found {self.members}")
        if not 0 <= self.seed <= MAX_SEED:
            raise ConfigError(f"seed must be an integer from 0 to {MAX_SEED} (2**64 - 1), found {self.seed}")
        if self.epochs > MAX_EPOCHS:
            raise ConfigError(f"epochs must be <= {MAX_EPOCHS}, found {self.epochs}")
        if self.members > MAX_MEMBERS:
            raise ConfigError(f"members must be <= {MAX_MEMBERS}, found {self.members}")
        if not self.lr > 0 or not math.isfinite(self.lr):
            raise ConfigError(f"lr must be a positive number, found {self.lr}")
        if self.grad_clip is not None and not self.grad_clip > 0:
            raise ConfigError(f"grad_clip must be a positive number or None, found {self.grad_clip}")
        for name in ("max_windows", "max_episodes"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1 or None, found {getattr(self, name)}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"device must be auto, cpu or cuda, found {self.device!r}")
        if not 0 <= self.min_rel_improvement < 1:
            raise ConfigError(f"min_rel_improvement must be in [0, 1), found {self.min_rel_improvement}")
        self.widths = tuple(int(w) for w in self.widths)
        if len(self.widths) != 3 or not all(1 <= w <= MAX_WIDTH for w in self.widths):
            raise ConfigError(f"widths must be three channel counts from 1 to {MAX_WIDTH}, found {self.widths}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d
