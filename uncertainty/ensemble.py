"""K independently initialised predictors run as one fused forward pass, and their disagreement.

The members' parameters live stacked, one tensor per parameter with a leading
member axis ``K``. ``forward`` runs all K members as one grouped convolution per
layer on channels-last activations whose channels are grouped by member
(``grouped_forward``); member-wise concatenations (skips, the 2x upsample) are
built in one NHWC copy each. ``forward_vmap`` does the same through
``torch.vmap`` over ``torch.func.functional_call``; ``forward_loop`` runs the
same weights member by member, as K ordinary ``Predictor`` calls. Both exist to
check the fused pass and to benchmark it. ``forward_dist`` adds the members'
predicted log-variances when they have a variance head (``predict_variance``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import torch
from torch import nn
from torch.func import functional_call
from torch.nn import functional as F

from uncertainty.errors import ConfigError, DataError
from uncertainty.model import Predictor, PredictorConfig, head_input, squash_logvar


def default_device() -> torch.device:
    """CUDA when there is one, CPU otherwise."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def frames_to_tensor(frames: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(T,H,W,3) uint8 -> (T,3,H,W) float32 in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(frames)).to(device)  # (T, H, W, 3) uint8
    return t.permute(0, 3, 1, 2).float().div_(255.0)              # (T, 3, H, W)


#: On CPU the fused pass's activations are K times wider than one member's, so at an episode's batch
#: (~48 windows) they fall out of cache: slices of 16 ran ~1.5x more frames/s than one call of 48 on
#: the 2-core development machine (BENCHMARKS.md). Training (autograd) and CUDA take the whole batch.
CPU_SLICE = 16


class Ensemble(nn.Module):
    """K predictors with stacked parameters; ``forward`` returns every member's prediction (K,B,3,H,W)."""

    def __init__(self, config: PredictorConfig, members: int = 5, seed: int = 0) -> None:
        super().__init__()
        if members < 1:
            raise ConfigError(f"members must be >= 1, found {members}")
        self.config = config
        self.members = members
        self.seed = seed
        self.version = ""
        """Registry version it was loaded from ('' for a fresh or unsaved ensemble)."""
        self.cpu_slice = CPU_SLICE
        """Windows per fused call on CPU in inference (0: the whole batch at once); see ``CPU_SLICE``."""
        gen = torch.Generator().manual_seed(seed)
        # One predictor re-initialised per member (the same draws as K predictors): its buffers (coordinate
        # grids, 8 MiB at 1024 px) exist once, not K times, whatever member count a checkpoint claims.
        net = Predictor(config)
        self.names = [n for n, _ in net.named_parameters()]
        drawn: list[list[torch.Tensor]] = []
        for _ in range(members):
            net.reset_parameters(gen)
            drawn.append([p.detach().clone() for p in net.parameters()])
        # The template holds no weights of its own that matter: functional_call swaps them in.
        # Kept out of the module tree (not a submodule), so .to(device) leaves it on "meta".
        self.__dict__["template"] = copy.deepcopy(net).to("meta")
        self.params = nn.ParameterList(
            nn.Parameter(torch.stack([member[i] for member in drawn]))  # (K, ...)
            for i in range(len(self.names)))
        del drawn
        self.buffer_names = [n for n, _ in net.named_buffers()]
        for name, buf in net.named_buffers():
            self.register_buffer("buf_" + name, buf, persistent=False)
        # Action normalisation (raw world units -> roughly zero mean, unit std); set from training data.
        self.register_buffer("action_mean", torch.zeros(config.action_dim))
        self.register_buffer("action_std", torch.ones(config.action_dim))

    # -- parameters -------------------------------------------------------------------------------
    def _buffers_dict(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, "buf_" + name) for name in self.buffer_names}

    def member_params(self, k: int) -> dict[str, torch.Tensor]:
        """Member k's parameters as a name -> tensor dict (views into the stacked tensors)."""
        return {name: p[k] for name, p in zip(self.names, self.params)}

    def member(self, k: int) -> Predictor:
        """A standalone ``Predictor`` holding a copy of member k's weights."""
        net = Predictor(self.config).to(self.action_mean.device)
        net.load_state_dict({n: t.detach().clone() for n, t in self.member_params(k).items()})
        return net

    def set_action_stats(self, mean: np.ndarray, std: np.ndarray) -> None:
        """Sets the normalisation of raw actions: (a - mean) / std, per dimension."""
        mean = torch.as_tensor(np.asarray(mean, dtype=np.float32))
        std = torch.as_tensor(np.asarray(std, dtype=np.float32))
        if mean.shape != (self.config.action_dim,) or std.shape != (self.config.action_dim,):
            raise ConfigError(f"action stats must have shape ({self.config.action_dim},), "
                              f"found {tuple(mean.shape)} and {tuple(std.shape)}")
        if not torch.all(std > 0):
            raise ConfigError(f"action std must be > 0, found {std.tolist()}")
        self.action_mean.copy_(mean)
        self.action_std.copy_(std)

    def normalize_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """Raw actions (..., A) in world units -> normalised actions (..., A)."""
        return (actions - self.action_mean) / self.action_std

    @property
    def device(self) -> torch.device:
        return self.action_mean.device

    # -- forward passes ---------------------------------------------------------------------------
    def _one(self, params: dict, context: torch.Tensor, action: torch.Tensor, with_variance: bool = False):
        return functional_call(self.template, (params, self._buffers_dict()), (context, action),
                               {"with_variance": with_variance})

    def forward(self, context: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Fused pass over all members as grouped convolutions (one call per layer for all K).

        context: (B,C,3,H,W) shared by all members, or (K,B,C,3,H,W) one per member;
        action: (B,A) or (K,B,A), normalised. Returns (K,B,3,H,W).
        On CPU without autograd the batch goes through in slices of ``cpu_slice`` windows (see there).
        """
        return self._fused(context, action, with_variance=False)

    def forward_dist(self, context: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward`` plus each member's predicted log-variance: two (K,B,3,H,W) tensors.

        Raises ``ConfigError`` unless the members have a variance head (``predict_variance``).
        """
        if not self.config.predict_variance:
            raise ConfigError("this ensemble has no variance head (predict_variance is false)")
        return self._fused(context, action, with_variance=True)

    def _fused(self, context: torch.Tensor, action: torch.Tensor, with_variance: bool):
        params, buffers = dict(zip(self.names, self.params)), self._buffers_dict()
        b = context.shape[-5]
        step = self.cpu_slice
        if step <= 0 or b <= step or context.device.type != "cpu" or torch.is_grad_enabled():
            return grouped_forward(params, buffers, self.config, self.members, context, action, with_variance)
        outs = []
        for lo in range(0, b, step):
            ctx = context[lo:lo + step] if context.dim() == 5 else context[:, lo:lo + step]
            act = action[lo:lo + step] if action.dim() == 2 else action[:, lo:lo + step]
            out = grouped_forward(params, buffers, self.config, self.members, ctx, act, with_variance)
            outs.append(out if with_variance else (out,))                              # (K, b', 3, H, W) each
        cat = tuple(torch.cat(parts, dim=1) for parts in zip(*outs))                   # (K, B, 3, H, W) each
        return cat if with_variance else cat[0]

    def forward_vmap(self, context: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Fused pass via ``torch.vmap`` over ``functional_call`` (same result; slower on CPU)."""
        params = dict(zip(self.names, self.params))
        ctx_dim = 0 if context.dim() == 6 else None
        act_dim = 0 if action.dim() == 3 else None
        return torch.vmap(self._one, in_dims=(0, ctx_dim, act_dim))(params, context, action)

    def forward_loop(self, context: torch.Tensor, action: torch.Tensor, with_variance: bool = False):
        """The same predictions as ``forward`` (``forward_dist`` with ``with_variance``), one member at a time.

        For tests and benchmarks.
        """
        outs = []
        for k in range(self.members):
            ctx = context[k] if context.dim() == 6 else context
            act = action[k] if action.dim() == 3 else action
            out = self._one(self.member_params(k), ctx, act, with_variance)  # (B, 3, H, W), or two
            outs.append(out if with_variance else (out,))
        stacked = tuple(torch.stack(parts) for parts in zip(*outs))           # (K, B, 3, H, W) each
        return stacked if with_variance else stacked[0]

    def rollout(self, context: torch.Tensor, actions: torch.Tensor, fused: bool | str = True) -> torch.Tensor:
        """Each member rolls out on its own predictions.

        context (B,C,3,H,W) shared, actions (B,H,A) normalised -> (K,B,H,3,H,W), clamped to [0,1].
        """
        step = {True: self.forward, False: self.forward_loop, "vmap": self.forward_vmap}[fused]
        k = self.members
        ctx = context                                                    # (B, C, 3, H, W): shared at first
        preds = []
        for i in range(actions.shape[1]):
            nxt = step(ctx, actions[:, i]).clamp(0.0, 1.0)               # (K, B, 3, H, W)
            preds.append(nxt)
            if ctx.dim() == 5:
                ctx = ctx.unsqueeze(0).expand(k, *ctx.shape)             # (K, B, C, 3, H, W)
            ctx = torch.cat([ctx[:, :, 1:], nxt[:, :, None]], dim=2)     # (K, B, C, 3, H, W)
        return torch.stack(preds, dim=2)                                 # (K, B, H, 3, H, W)

    # -- disagreement -----------------------------------------------------------------------------
    @torch.inference_mode()
    def disagreement(self, frames: np.ndarray, actions: np.ndarray, horizon: int = 1,
                     fused: bool | str = True, batch_size: int = 256) -> np.ndarray:
        """Per-step disagreement of one episode: (T,) float64.

        frames (T,H,W,3) uint8, actions (T,2) raw world units. For step t the members
        predict frames t+1..t+horizon (each on its own predictions); the score is the
        variance across members, averaged over pixels and over the horizon's steps.
        Steps without ``C-1`` earlier frames or without ``horizon`` successors are NaN.
        Raises ``DataError`` on mismatched shapes.
        """
        return self.score_steps(frames, actions, horizon, member_variance, fused, batch_size)

    @torch.inference_mode()
    def score_steps(self, frames: np.ndarray, actions: np.ndarray, horizon: int, score: StepScore,
                    fused: bool | str = True, batch_size: int = 256) -> np.ndarray:
        """Per-step scores of one episode's member rollouts: (T,) float64, NaN where a step has none.

        Every valid step's context is rolled out ``horizon`` steps by each member, in batches;
        ``score(preds (K,B,Hz,3,H,W), context (B,C,3,H,W), real (B,Hz,3,H,W)) -> (B,)`` reduces a
        batch (``disagreement`` is the plain variance). Raises ``DataError`` on mismatched shapes.
        """
        def rolled_out(ctx: torch.Tensor, act: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
            return score(self.rollout(ctx, act, fused=fused), ctx, real)               # (B,)

        return self.score_windows(frames, actions, horizon, rolled_out, batch_size)

    @torch.inference_mode()
    def score_windows(self, frames: np.ndarray, actions: np.ndarray, horizon: int, score: WindowScore,
                      batch_size: int = 256) -> np.ndarray:
        """Per-step scores of one episode's windows: (T,) float64, NaN where a step has none.

        ``score(context (B,C,3,H,W), normalised actions (B,Hz,2), real next frames (B,Hz,3,H,W)) -> (B,)``
        reduces each batch of the steps with ``C-1`` earlier frames and ``horizon`` successors
        (``score_steps`` rolls the members out in it). Raises ``DataError`` on mismatched shapes.
        """
        windows = episode_windows(frames, actions, self.config, horizon)
        out = np.full(len(frames), np.nan)
        if windows is None:
            return out
        steps, ctx_idx, act_idx = windows
        x = frames_to_tensor(frames, self.device)                                        # (T, 3, H, W)
        a = self.normalize_actions(torch.as_tensor(actions, dtype=torch.float32, device=self.device))
        scores = []
        for lo in range(0, len(steps), batch_size):
            ctx = x[torch.as_tensor(ctx_idx[lo:lo + batch_size], device=self.device)]   # (B, C, 3, H, W)
            act_i = torch.as_tensor(act_idx[lo:lo + batch_size], device=self.device)    # (B, Hz)
            scores.append(score(ctx, a[act_i], x[act_i + 1]))                          # (B,)
        out[steps] = torch.cat(scores).double().cpu().numpy()
        return out


#: Reduces a batch of member rollouts to one score per step: (preds, context, real next frames) -> (B,).
StepScore = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
#: Scores a batch of windows, one score per step: (context, normalised actions, real next frames) -> (B,).
WindowScore = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def member_variance(preds: torch.Tensor, context: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """The disagreement of a batch of member rollouts (a ``StepScore``): the variance across members, averaged
    over the horizon and the pixels."""
    return preds.var(dim=0, unbiased=False).mean(dim=(1, 2, 3, 4))                     # (B,)


def episode_windows(frames: np.ndarray, actions: np.ndarray, config: PredictorConfig,
                    horizon: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Valid steps of an episode and their index arrays, or None when the episode is too short.

    Returns steps (N,), context frame indices (N,C) and action indices (N,horizon).
    Raises ``DataError`` when frames and actions disagree in length or image size.
    """
    if horizon < 1:
        raise ConfigError(f"horizon must be >= 1, found {horizon}")
    t = len(frames)
    if frames.ndim != 4 or frames.shape[1:] != (config.image_size, config.image_size, 3):
        raise DataError(f"frames must be (T,{config.image_size},{config.image_size},3), found {frames.shape}")
    if actions.shape != (t, config.action_dim):
        raise DataError(f"actions must be ({t},{config.action_dim}), found {actions.shape}")
    c = config.context
    steps = np.arange(c - 1, t - horizon)                      # (N,) every step with context and successors
    if len(steps) == 0:
        return None
    ctx_idx = steps[:, None] + np.arange(-c + 1, 1)[None, :]   # (N, C)
    act_idx = steps[:, None] + np.arange(horizon)[None, :]     # (N, horizon)
    return steps, ctx_idx, act_idx


def _to_cl(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous(memory_format=torch.channels_last)


def _cat_members(parts: list[torch.Tensor], k: int) -> torch.Tensor:
    """Member-wise channel concatenation of (B, K*c_i, h, w) tensors -> (B, K*sum(c_i), h, w), channels-last.

    Member m's block of the result holds every part's member-m channels, in order,
    as a grouped convolution expects. Done in NHWC so it is one copy.
    """
    b, _, h, w = parts[0].shape
    nhwc = [_to_cl(x).permute(0, 2, 3, 1).reshape(b, h, w, k, -1) for x in parts]  # (B, h, w, K, c_i)
    return torch.cat(nhwc, dim=-1).reshape(b, h, w, -1).permute(0, 3, 1, 2)      # (B, K*sum c_i, h, w)


def _upsample_cat_members(low: torch.Tensor, skip: torch.Tensor, k: int) -> torch.Tensor:
    """``_cat_members([nearest_2x(low), skip])`` in one buffer: the 2x upsample is a broadcast copy into it.

    low (B, K*c1, h, w), skip (B, K*c2, 2h, 2w) -> (B, K*(c1+c2), 2h, 2w), channels-last.
    """
    b, _, h, w = low.shape
    c1, c2 = low.shape[1] // k, skip.shape[1] // k
    buf = low.new_empty(b, h, 2, w, 2, k, c1 + c2)                                   # (B, h, 2, w, 2, K, c)
    src = _to_cl(low).permute(0, 2, 3, 1).reshape(b, h, 1, w, 1, k, c1)             # (B, h, 1, w, 1, K, c1)
    buf[..., :c1].copy_(src.expand(-1, -1, 2, -1, 2, -1, -1))
    buf[..., c1:].copy_(_to_cl(skip).permute(0, 2, 3, 1).reshape(b, h, 2, w, 2, k, c2))
    return buf.reshape(b, 2 * h, 2 * w, -1).permute(0, 3, 1, 2)                     # (B, K*c, 2h, 2w)


def _gconv(x: torch.Tensor, p: dict, name: str, k: int, stride: int = 1, padding: int = 1,
           shared: bool = False) -> torch.Tensor:
    """Layer ``name`` of all K members as one convolution over (B, K*c, h, w) member-grouped input.

    ``shared``: x is (B, c, h, w), the same for every member, and the K members' filters
    are stacked into one ordinary convolution with K*Cout outputs. Channels-last input
    makes oneDNN's grouped convolution about as fast per FLOP as a plain one.
    """
    w = p[name + ".weight"]                                          # (K, Cout, Cin, kh, kw)
    if x.shape[1] != (w.shape[2] if shared else k * w.shape[2]):
        raise ConfigError(f"layer {name} expects {w.shape[2]} input channels per member, "
                          f"found {x.shape[1] if shared else x.shape[1] / k}")
    return F.conv2d(_to_cl(x), w.reshape(-1, *w.shape[2:]), p[name + ".bias"].reshape(-1),  # (K*Cout, Cin, kh, kw)
                    stride=stride, padding=padding, groups=1 if shared else k)  # (B, K*Cout, h', w')


def _silu(x: torch.Tensor) -> torch.Tensor:
    # In place when no graph is recorded: saves an allocation and a pass over memory per layer.
    return F.silu(x, inplace=not torch.is_grad_enabled())


def grouped_forward(p: dict, buffers: dict, config: PredictorConfig, k: int,
                    context: torch.Tensor, action: torch.Tensor, with_variance: bool = False):
    """``Predictor.forward`` for K stacked members at once; see ``Ensemble.forward`` for shapes.

    ``with_variance``: returns (frames, log-variances), both (K,B,3,H,W); without it a variance
    head is not run at all.
    """
    if context.dim() == 5 and action.dim() == 3:
        context = context.expand(k, *context.shape)                  # (K, B, C, 3, H, W)
    shared = context.dim() == 5
    if shared:
        b, c, _, h, w = context.shape
    else:
        _, b, c, _, h, w = context.shape
    if config.context != c or config.image_size != h or config.image_size != w:
        raise ConfigError(f"context must be (...,{config.context},3,{config.image_size},{config.image_size}),"
                          f" found {tuple(context.shape)}")
    act = action.expand(k, *action.shape) if action.dim() == 2 else action  # (K, B, A)
    if shared:
        # Built directly in NHWC: (B, H, W, 3C+2+A), viewed as a channels-last (B, 3C+2+A, H, W).
        x = torch.cat([context.permute(0, 3, 4, 1, 2).reshape(b, h, w, c * 3) * 2 - 1,  # centred
                       buffers["coords_full"].permute(1, 2, 0).expand(b, -1, -1, -1),
                       action[:, None, None, :].expand(-1, h, w, -1)], dim=-1).permute(0, 3, 1, 2)
        last = context[:, -1].unsqueeze(0)                           # (1, B, 3, H, W)
    else:
        x = context.permute(1, 4, 5, 0, 2, 3).reshape(b, h, w, k, c * 3) * 2 - 1  # (B, H, W, K, 3C), centred
        x = torch.cat([x, buffers["coords_full"].permute(1, 2, 0)[None, :, :, None].expand(b, -1, -1, k, -1),
                       act.permute(1, 0, 2)[:, None, None].expand(-1, h, w, -1, -1)], dim=-1)  # (B,H,W,K,3C+2+A)
        x = x.reshape(b, h, w, -1).permute(0, 3, 1, 2)               # (B, K*(3C+2+A), H, W) channels-last
        last = context[:, :, -1]                                     # (K, B, 3, H, W)
    e1 = _silu(_gconv(x, p, "enc1", k, 2, 1, shared=shared))        # (B, K*w0, H/2, W/2)
    e2 = _silu(_gconv(e1, p, "enc2", k, 2, 1))                      # (B, K*w1, H/4, W/4)
    e3 = _silu(_gconv(e2, p, "enc3", k, 2, 1))                      # (B, K*w2, H/8, W/8)
    hid = F.silu(torch.baddbmm(p["film.0.bias"][:, None], act, p["film.0.weight"].transpose(1, 2)))  # (K, B, Ah)
    film = torch.baddbmm(p["film.2.bias"][:, None], hid, p["film.2.weight"].transpose(1, 2))         # (K, B, 2*w2)
    gamma, beta = film.permute(1, 0, 2).chunk(2, dim=-1)            # (B, K, w2) each
    hl, wl = e3.shape[-2:]
    z = torch.addcmul(beta.reshape(b, -1, 1, 1), e3, 1 + gamma.reshape(b, -1, 1, 1))  # (B, K*w2, h, w)
    side = torch.cat([act.permute(1, 0, 2)[:, None, None].expand(-1, hl, wl, -1, -1),            # (B, h, w, K, A)
                      buffers["coords_low"].permute(1, 2, 0)[None, :, :, None].expand(b, -1, -1, k, -1)],
                     dim=-1).reshape(b, hl, wl, -1).permute(0, 3, 1, 2)  # (B, K*(A+2), h, w) channels-last
    z = _silu(_gconv(_cat_members([z, side], k), p, "mid1", k))      # (B, K*w2, h, w)
    z = _silu(_gconv(z, p, "mid2", k))                               # (B, K*w2, h, w)
    d = _silu(_gconv(_upsample_cat_members(z, e2, k), p, "dec2", k))  # (B, K*w1, H/4, W/4)
    d = _silu(_gconv(_upsample_cat_members(d, e1, k), p, "dec1", k))  # (B, K*w0, H/2, W/2)
    out = _to_cl(_gconv(d, p, "out", k)).permute(0, 2, 3, 1)        # (B, H/2, W/2, K*12)
    frames = _add_shuffled(last, out, k)                             # (K, B, 3, H, W)
    if not with_variance:
        return frames
    v = _silu(_gconv(head_input(d), p, "var1", k))                  # (B, K*w0, H/2, W/2)
    raw = _add_shuffled(None, _to_cl(_gconv(v, p, "var_out", k)).permute(0, 2, 3, 1), k)  # (K, B, 3, H, W)
    return frames, squash_logvar(raw)                                # (K, B, 3, H, W) each


def _add_shuffled(base: torch.Tensor | None, out: torch.Tensor, k: int) -> torch.Tensor:
    """Each member's pixel-shuffled 12 output channels (plus ``base``): (B, h, w, K*12) -> (K, B, 3, 2h, 2w).

    ``base`` is (K or 1, B, 3, 2h, 2w) or None. pixel_shuffle semantics: channel j*4 + 2*i + jj of a
    member goes to colour j, offset (i, jj).
    """
    b, h, w = out.shape[:3]
    shuffled = out.reshape(b, h, w, k, 3, 2, 2).permute(3, 0, 4, 1, 5, 2, 6)  # (K, B, 3, h, 2, w, 2)
    if base is None:
        return shuffled.reshape(k, b, 3, 2 * h, 2 * w)
    base = base.unflatten(3, (h, 2)).unflatten(5, (w, 2))                    # (K or 1, B, 3, h, 2, w, 2)
    return (base + shuffled).reshape(k, b, 3, 2 * h, 2 * w)
