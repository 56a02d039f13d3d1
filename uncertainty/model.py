"""The world model: a deterministic, action-conditioned convolutional next-frame predictor.

One member of the ensemble. It looks at the last ``C`` frames (stacked along
channels, plus two coordinate channels so convolutions know *where* they are),
and decodes the change from the last frame through a small U-Net. Actions are
absolute pusher targets, so the net has to relate them to positions: they enter
as constant channels next to the coordinates (one linear layer can then form
the offset from every pixel to the target, whatever the affine world-to-image
map), and again at the bottleneck through FiLM and as broadcast channels.

Imports nothing of ours but the package's errors: no training, storage or I/O.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from uncertainty.errors import ConfigError


# Convolutions on CUDA in full float32. cuDNN's default, TF32 (inputs rounded to 10 mantissa bits), made the fused
# pass differ from the members one by one by up to 7e-4 on an H100, where the fused pass must give their
# predictions within 1e-5 (BENCHMARKS.md, "On a GPU"). Process-wide, and so for every model of ours; matrix
# products are full float32 already (torch's default).
torch.backends.cudnn.allow_tf32 = False

#: Largest frame a predictor takes: the catalog's (``storage.records.MAX_FRAME_SIZE``; this module imports
#: nothing of storage). Beyond it a config read from a file would allocate its coordinate grids unchecked.
MAX_IMAGE_SIZE = 1024


@dataclass(frozen=True)
class PredictorConfig:
    """Shape of one predictor; passed whole, stored whole in checkpoints."""

    image_size: int = 64
    """Frame height and width in pixels (a multiple of 8, at most ``MAX_IMAGE_SIZE``)."""
    context: int = 2
    """How many past frames the predictor sees (C)."""
    action_dim: int = 2
    """Length of the action vector."""
    widths: tuple[int, int, int] = (16, 32, 64)
    """Channels at 1/2, 1/4 and 1/8 of the image size."""
    action_hidden: int = 64
    """Hidden units of the action MLP that produces the FiLM scale and shift."""
    predict_variance: bool = False
    """Also predict a per-pixel log-variance of the next frame (see ``Predictor.forward``)."""

    def __post_init__(self) -> None:
        for name in ("image_size", "context", "action_dim", "action_hidden"):
            object.__setattr__(self, name, _whole(name, getattr(self, name)))
        if not 8 <= self.image_size <= MAX_IMAGE_SIZE or self.image_size % 8:
            raise ConfigError(f"image_size must be a multiple of 8 in [8, {MAX_IMAGE_SIZE}], found {self.image_size}")
        if self.context < 1:
            raise ConfigError(f"context must be >= 1, found {self.context}")
        if self.action_dim < 1:
            raise ConfigError(f"action_dim must be >= 1, found {self.action_dim}")
        widths = tuple(_whole("widths", w) for w in self.widths)
        if len(widths) != 3 or min(widths) < 1:
            raise ConfigError(f"widths must be three positive channel counts, found {self.widths}")
        object.__setattr__(self, "widths", widths)
        if not isinstance(self.predict_variance, bool):
            raise ConfigError(f"predict_variance must be true or false, found {self.predict_variance!r}")
        if self.action_hidden < 1:
            raise ConfigError(f"action_hidden must be >= 1, found {self.action_hidden}")

    def to_dict(self) -> dict:
        return {"image_size": self.image_size, "context": self.context, "action_dim": self.action_dim,
                "widths": list(self.widths), "action_hidden": self.action_hidden,
                "predict_variance": self.predict_variance}

    @classmethod
    def from_dict(cls, d: dict) -> "PredictorConfig":
        """Rebuild from ``to_dict``; raises ``ConfigError`` on unknown or bad fields."""
        known = {"image_size", "context", "action_dim", "widths", "action_hidden", "predict_variance"}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"unknown predictor config fields {sorted(unknown)}")
        d = dict(d)
        if "widths" in d:
            d["widths"] = tuple(d["widths"])
        return cls(**d)


def _whole(name: str, value: object) -> int:
    """``value`` as an int; ``ConfigError`` for anything else (a float, a string, a bool), which a config read
    from a file may hold and torch's layers refuse with a TypeError of their own."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{name}: expected an integer, found {value!r}")
    return int(value)


#: Range of the predicted log-variance: ``LOGVAR_MID +- LOGVAR_HALF_RANGE`` (a tanh squashes the raw output),
#: i.e. standard deviations from ~1e-3 to 1 of a [0, 1] pixel; it starts at the middle.
LOGVAR_MID = -7.0
LOGVAR_HALF_RANGE = 7.0


#: Share of the variance head's gradient that reaches the layers it shares with the frame prediction.
#: At 1 the trunk serves the head too much (h1 PSNR gain 2.3-2.9 dB instead of 3.0), at 0 (detached) the
#: head has only features made for the frame and ranks the error poorly (Spearman 0.04-0.36); at 0.3 the
#: trunk learns from the error too and both gain (+3.44 / +3.55 dB, Spearman 0.52 / 0.59; BENCHMARKS.md).
HEAD_GRAD_SHARE = 0.3


def head_input(features: torch.Tensor) -> torch.Tensor:
    """``features`` in the forward pass; in the backward pass only ``HEAD_GRAD_SHARE`` of the gradient
    flows into them (read at call time)."""
    return features * HEAD_GRAD_SHARE + features.detach() * (1 - HEAD_GRAD_SHARE)


def squash_logvar(raw: torch.Tensor) -> torch.Tensor:
    """Raw variance-head output -> log-variance in ``LOGVAR_MID +- LOGVAR_HALF_RANGE``, smoothly."""
    return LOGVAR_MID + LOGVAR_HALF_RANGE * torch.tanh(raw / LOGVAR_HALF_RANGE)


def coord_grid(size: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(2, size, size) pixel-centre coordinates in [-1, 1]: channel 0 is x (columns), 1 is y (rows)."""
    ax = (torch.arange(size, device=device, dtype=dtype) + 0.5) / size * 2 - 1  # (S,)
    ys, xs = torch.meshgrid(ax, ax, indexing="ij")  # (S, S) each
    return torch.stack([xs, ys])  # (2, S, S)


class Predictor(nn.Module):
    """frames[t-C+1..t], action[t] -> frames[t+1], predicting the residual from frames[t]."""

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.config = config
        c = config
        w0, w1, w2 = c.widths
        self.register_buffer("coords_full", coord_grid(c.image_size), persistent=False)
        self.register_buffer("coords_low", coord_grid(c.image_size // 8), persistent=False)
        self.enc1 = nn.Conv2d(3 * c.context + 2 + c.action_dim, w0, 4, stride=2, padding=1)  # -> S/2
        self.enc2 = nn.Conv2d(w0, w1, 4, stride=2, padding=1)                 # -> S/4
        self.enc3 = nn.Conv2d(w1, w2, 4, stride=2, padding=1)                 # -> S/8
        self.film = nn.Sequential(nn.Linear(c.action_dim, c.action_hidden), nn.SiLU(),
                                  nn.Linear(c.action_hidden, 2 * w2))
        self.mid1 = nn.Conv2d(w2 + c.action_dim + 2, w2, 3, padding=1)
        self.mid2 = nn.Conv2d(w2, w2, 3, padding=1)
        self.dec2 = nn.Conv2d(w2 + w1, w1, 3, padding=1)  # at S/4, with the enc2 skip
        self.dec1 = nn.Conv2d(w1 + w0, w0, 3, padding=1)  # at S/2, with the enc1 skip
        self.out = nn.Conv2d(w0, 3 * 4, 3, padding=1)     # at S/2, pixel-shuffled to S
        if c.predict_variance:
            # Reads the decoder's features (passing back HEAD_GRAD_SHARE of its gradient) to predict the error.
            self.var1 = nn.Conv2d(w0, w0, 3, padding=1)
            self.var_out = nn.Conv2d(w0, 3 * 4, 3, padding=1)  # raw log-variance, pixel-shuffled to S
        self.reset_parameters(None)

    def reset_parameters(self, generator: torch.Generator | None) -> None:
        """PyTorch's default init, drawn from ``generator`` so members are reproducible; zero output layer."""
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5), generator=generator)
                fan_in = m.weight[0].numel()
                bound = 1 / math.sqrt(fan_in)
                nn.init.uniform_(m.bias, -bound, bound, generator=generator)
        # Start as copy-last-frame-ish with small random output: members still differ.
        # A variance head likewise starts near LOGVAR_MID everywhere.
        with torch.no_grad():
            for out in (self.out, getattr(self, "var_out", None)):
                if out is not None:
                    out.weight.mul_(0.1)
                    out.bias.zero_()

    def forward(self, context: torch.Tensor, action: torch.Tensor,
                with_variance: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """context (B,C,3,H,W) in [0,1], action (B,A) normalised -> predicted next frame (B,3,H,W).

        ``with_variance`` (needs ``config.predict_variance``): returns (next frame, log-variance), both
        (B,3,H,W): the model's own estimate of its squared error per pixel, trained by a Gaussian NLL.
        The head reads the decoder's features and passes ``HEAD_GRAD_SHARE`` of its gradient back into
        them; asking for it changes no predicted frame.
        """
        if with_variance and not self.config.predict_variance:
            raise ConfigError("this predictor has no variance head (predict_variance is false)")
        b, c, _, h, w = context.shape
        if c != self.config.context or h != self.config.image_size or w != self.config.image_size:
            raise ConfigError(f"context must be (B,{self.config.context},3,{self.config.image_size},"
                              f"{self.config.image_size}), found {tuple(context.shape)}")
        last = context[:, -1]                                   # (B, 3, H, W)
        x = context.reshape(b, c * 3, h, w) * 2 - 1             # (B, 3C, H, W), centred: faster to fit
        a_full = action[:, :, None, None].expand(-1, -1, h, w)  # (B, A, H, W)
        x = torch.cat([x, self.coords_full.expand(b, -1, -1, -1), a_full], dim=1)  # (B, 3C+2+A, H, W)
        e1 = F.silu(self.enc1(x))                               # (B, w0, H/2, W/2)
        e2 = F.silu(self.enc2(e1))                              # (B, w1, H/4, W/4)
        e3 = F.silu(self.enc3(e2))                              # (B, w2, H/8, W/8)
        gamma, beta = self.film(action).chunk(2, dim=-1)        # (B, w2) each
        z = e3 * (1 + gamma[:, :, None, None]) + beta[:, :, None, None]  # (B, w2, H/8, W/8)
        hl, wl = z.shape[-2:]
        a_map = action[:, :, None, None].expand(-1, -1, hl, wl)  # (B, A, H/8, W/8)
        z = torch.cat([z, a_map, self.coords_low.expand(b, -1, -1, -1)], dim=1)  # (B, w2+A+2, H/8, W/8)
        z = F.silu(self.mid1(z))                                # (B, w2, H/8, W/8)
        z = F.silu(self.mid2(z))                                # (B, w2, H/8, W/8)
        d = F.interpolate(z, scale_factor=2.0, mode="nearest")  # (B, w2, H/4, W/4)
        d = F.silu(self.dec2(torch.cat([d, e2], dim=1)))        # (B, w1, H/4, W/4)
        d = F.interpolate(d, scale_factor=2.0, mode="nearest")  # (B, w1, H/2, W/2)
        d = F.silu(self.dec1(torch.cat([d, e1], dim=1)))        # (B, w0, H/2, W/2)
        delta = F.pixel_shuffle(self.out(d), 2)                 # (B, 12, H/2, W/2) -> (B, 3, H, W)
        if not with_variance:
            return last + delta
        v = F.silu(self.var1(head_input(d)))                    # (B, w0, H/2, W/2)
        return last + delta, squash_logvar(F.pixel_shuffle(self.var_out(v), 2))  # (B, 3, H, W) each

    def rollout(self, context: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Autoregressive prediction: context (B,C,3,H,W), actions (B,H,A) -> frames (B,H,3,H,W).

        Each prediction is clamped to [0, 1] and fed back as the newest context frame.
        """
        preds = []
        ctx = context
        for i in range(actions.shape[1]):
            nxt = self(ctx, actions[:, i]).clamp(0.0, 1.0)      # (B, 3, H, W)
            preds.append(nxt)
            ctx = torch.cat([ctx[:, 1:], nxt[:, None]], dim=1)  # (B, C, 3, H, W)
        return torch.stack(preds, dim=1)                        # (B, H, 3, H, W)
