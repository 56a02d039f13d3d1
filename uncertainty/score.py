"""Scoring an episode: where does the ensemble disagree, and what would it take to go back there?

Each top state carries everything the planner needs to build a collection
request: the simulator state at that step (velocities included), the episode's
start state, and the action prefix that led from the start to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from storage.records import STATE_COLUMN, Episode
from uncertainty.ensemble import Ensemble, member_variance
from uncertainty.errors import ConfigError


@dataclass
class ScoredState:
    """One uncertain state of an episode, ready to become a collection request."""

    step: int
    """Step t: the state observed before actions[t]."""
    score: float
    """Disagreement at that step."""
    state: dict[str, Any]
    """Simulator state at step t in ``SimState.to_dict`` form."""
    start_state: dict[str, Any]
    """The episode's start state (``SimState.to_dict`` form)."""
    action_prefix: list[list[float]]
    """actions[:step]: replayed from ``start_state`` they lead to ``state``."""
    shape: str
    """Object shape."""
    physics: dict[str, float]
    """Physics parameters of the episode."""
    episode_id: str
    """The scored episode."""

    def to_json(self) -> dict[str, Any]:
        return {"step": self.step, "score": self.score, "state": self.state, "start_state": self.start_state,
                "action_prefix": self.action_prefix, "shape": self.shape, "physics": self.physics,
                "episode_id": self.episode_id}


@dataclass
class EpisodeScore:
    """Per-step disagreement of one episode and its top states."""

    episode_id: str
    per_step: np.ndarray
    """(T,) disagreement, NaN where a step has too little context or no successor."""
    top: list[ScoredState] = field(default_factory=list)
    horizon: int = 1
    model_version: str = ""

    @property
    def mean(self) -> float:
        """Mean disagreement over the scored steps (NaN if none)."""
        ok = np.isfinite(self.per_step)
        return float(self.per_step[ok].mean()) if ok.any() else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {"episode_id": self.episode_id, "horizon": self.horizon, "model_version": self.model_version,
                "mean": self.mean, "per_step": [None if not np.isfinite(v) else float(v) for v in self.per_step],
                "top": [s.to_json() for s in self.top]}


def state_dict(row: np.ndarray, shape: str, physics: dict[str, float]) -> dict[str, Any]:
    """A ``states`` row (STATE_FIELDS order) as ``SimState.to_dict``'s form."""
    r = [float(v) for v in row]
    c = STATE_COLUMN
    return {"shape": shape, "agent": [r[c["agent_x"]], r[c["agent_y"]]],
            "agent_vel": [r[c["agent_vx"]], r[c["agent_vy"]]],
            "object": [r[c["obj_x"]], r[c["obj_y"]], r[c["obj_theta"]]],
            "object_vel": [r[c["obj_vx"]], r[c["obj_vy"]], r[c["obj_omega"]]],
            "physics": {k: float(v) for k, v in physics.items()}}


@torch.inference_mode()
def prediction_error(ensemble: Ensemble, frames: np.ndarray, actions: np.ndarray, horizon: int = 1,
                     batch_size: int = 256) -> np.ndarray:
    """Per-step squared error of the ensemble mean's next ``horizon`` frames against the recorded ones (each
    member rolling out on its own predictions), averaged over pixels and the horizon: (T,) float64, NaN
    where a step has no prediction or fewer than ``horizon`` successors (at 1: the eval's horizon-1 MSE, step
    by step). Raises ``DataError`` on mismatched shapes."""
    def mean_error(preds: torch.Tensor, context: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        return ((preds.mean(dim=0) - real) ** 2).mean(dim=(1, 2, 3, 4))                # (B,)

    return ensemble.score_steps(frames, actions, horizon, mean_error, batch_size=batch_size)


@torch.inference_mode()
def predicted_variance(ensemble: Ensemble, frames: np.ndarray, actions: np.ndarray, total: bool = False,
                       batch_size: int = 256) -> np.ndarray:
    """Per-step variance the members predict for their own next-frame error, averaged over members and
    pixels: (T,) float64, NaN where a step has no prediction. With ``total`` the members' disagreement is
    added: the mixture's total predictive variance, what eval's ``spearman_total`` ranks. Horizon 1 (the
    head predicts one step). Raises ``ConfigError`` when the members have no variance head
    (``predict_variance``), ``DataError`` on mismatched shapes."""
    if not ensemble.config.predict_variance:
        raise ConfigError("this ensemble has no variance head (predict_variance is false)")

    def variance(context: torch.Tensor, actions: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        preds, logvar = ensemble.forward_dist(context, actions[:, 0])                 # (K, B, 3, H, W) each
        out = logvar.exp().mean(dim=(0, 2, 3, 4))                                       # (B,)
        if total:  # the disagreement of the members' frames clamped to [0, 1], as a rollout's (and eval's)
            out = out + member_variance(preds.clamp(0.0, 1.0)[:, :, None], context, real)  # (B,)
        return out

    return ensemble.score_windows(frames, actions, 1, variance, batch_size)


@torch.inference_mode()
def change_disagreement(ensemble: Ensemble, frames: np.ndarray, actions: np.ndarray, horizon: int = 1,
                        threshold: float = 0.1, batch_size: int = 256) -> np.ndarray:
    """Per-step disagreement over the pixels that change: (T,) float64, NaN where a step has no score.

    Like ``Ensemble.disagreement`` (variance across members, members rolling out on their own
    predictions), but a pixel counts only where the frame changes over the horizon: where the
    recorded next frames or the ensemble's mean prediction differ from the last context frame
    by more than ``threshold`` (any channel). Static background and walls, where a weak ensemble
    disagrees for no useful reason, drop out; the score is the masked variance summed over
    pixels and divided by the frame's pixel count, so states where more moves (the object
    as well as the pusher) weigh more. Raises ``DataError`` on mismatched shapes.
    """
    def masked_variance(preds: torch.Tensor, context: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        last = context[:, -1:]                                                          # (B, 1, 3, H, W)
        moved = ((real - last).abs().amax(dim=2) > threshold) | \
                ((preds.mean(dim=0) - last).abs().amax(dim=2) > threshold)              # (B, Hz, H, W)
        var = preds.var(dim=0, unbiased=False).mean(dim=2)                              # (B, Hz, H, W)
        return (var * moved).mean(dim=(1, 2, 3))                                        # (B,)

    return ensemble.score_steps(frames, actions, horizon, masked_variance, batch_size=batch_size)


@torch.inference_mode()
def colour_disagreement(ensemble: Ensemble, frames: np.ndarray, actions: np.ndarray,
                        targets: Sequence[Sequence[float]], others: Sequence[Sequence[float]], horizon: int = 1,
                        grow: int = 1, batch_size: int = 256) -> np.ndarray:
    """Per-step disagreement over the pixels of one kind of thing, told by its colour: (T,) float64.

    A pixel counts where its colour, in the last context frame or in a recorded next frame, is nearer
    to one of ``targets`` than to every one of ``others`` (RGB, 0-255: e.g. the object's colours
    against the table's, the walls' and the pusher's), grown by ``grow`` pixels (its edges blend into
    the table), so the score follows what that thing does and leaves the rest of the scene (the
    pusher's free motion) out. Masked variance summed over pixels, divided by the frame's pixel
    count, as ``change_disagreement``.
    """
    if grow < 0:
        raise ConfigError(f"grow must be >= 0, found {grow}")

    def masked_variance(preds: torch.Tensor, context: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        mask = (colour_mask(context[:, -1:], targets, others)
                | colour_mask(real, targets, others)).float()                             # (B, Hz, H, W)
        if grow:
            mask = torch.nn.functional.max_pool2d(mask, 2 * grow + 1, stride=1, padding=grow)
        var = preds.var(dim=0, unbiased=False).mean(dim=2)                              # (B, Hz, H, W)
        return (var * mask).mean(dim=(1, 2, 3))                                         # (B,)

    return ensemble.score_steps(frames, actions, horizon, masked_variance, batch_size=batch_size)


def colour_mask(x: torch.Tensor, targets: Sequence[Sequence[float]], others: Sequence[Sequence[float]]) -> torch.Tensor:
    """(..., 3, H, W) frames in [0, 1] -> (..., H, W) bool: the pixel's colour is nearer one of ``targets``
    than every one of ``others`` (RGB, 0-255)."""
    refs = torch.tensor([*targets, *others], dtype=torch.float32, device=x.device) / 255.0      # (R, 3)
    dist = ((x.unsqueeze(-4) - refs.view(-1, 3, 1, 1)) ** 2).sum(dim=-3)                        # (..., R, H, W)
    return dist.argmin(dim=-3) < len(targets)


def object_moving(states: np.ndarray, horizon: int = 1, min_motion: float = 0.5) -> np.ndarray:
    """(T,) bool: the object's pose changes between step t and t+horizon (False past the end).

    ``states`` (T, STATE_DIM) in STATE_FIELDS order; motion is the object's displacement in
    world units plus its rotation in radians times 50 (about the largest shape's radius), so
    turning on the spot counts as moving.
    """
    out = np.zeros(len(states), dtype=bool)
    if len(states) <= horizon:
        return out
    c = STATE_COLUMN
    d = states[horizon:] - states[:-horizon]                                  # (T-h, STATE_DIM)
    turn = np.abs((d[:, c["obj_theta"]] + np.pi) % (2 * np.pi) - np.pi)
    out[:-horizon] = np.hypot(d[:, c["obj_x"]], d[:, c["obj_y"]]) + 50.0 * turn > min_motion
    return out


def pick_top(scores: np.ndarray, k: int, min_separation: int) -> list[int]:
    """Indices of up to k highest finite scores, no two closer than ``min_separation`` steps."""
    order = [i for i in np.argsort(-np.nan_to_num(scores, nan=-np.inf), kind="stable") if np.isfinite(scores[i])]
    chosen: list[int] = []
    for i in order:
        if len(chosen) == k:
            break
        if all(abs(int(i) - j) >= min_separation for j in chosen):
            chosen.append(int(i))
    return chosen


def score_episode(ensemble: Ensemble, episode: Episode, top_k: int = 5, horizon: int = 1,
                  min_separation: int = 5) -> EpisodeScore:
    """Per-step disagreement of ``episode`` and its ``top_k`` most uncertain, well-separated states.

    Raises ``ConfigError`` for a bad top_k / min_separation and ``DataError`` when
    the episode's frames do not fit the ensemble.
    """
    if top_k < 0 or min_separation < 1:
        raise ConfigError(f"top_k must be >= 0 and min_separation >= 1, found {top_k} and {min_separation}")
    per_step = ensemble.disagreement(episode.frames, episode.actions, horizon=horizon)  # (T,)
    meta = episode.meta
    start = dict(meta.start_state) if meta.start_state else state_dict(episode.states[0], meta.shape, meta.physics)
    top = [ScoredState(step=t, score=float(per_step[t]),
                       state=state_dict(episode.states[t], meta.shape, meta.physics),
                       start_state=start,
                       action_prefix=[[float(x), float(y)] for x, y in episode.actions[:t]],
                       shape=meta.shape, physics={k: float(v) for k, v in meta.physics.items()},
                       episode_id=meta.episode_id)
           for t in pick_top(per_step, top_k, min_separation)]
    return EpisodeScore(meta.episode_id, per_step, top, horizon, ensemble.version)
