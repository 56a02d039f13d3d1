"""Diversity: the normalised state space the active planner keeps its requests apart in.

``state_features`` maps a state (shape, agent, object pose, physics) to a vector; ``select_diverse`` keeps the
highest-scoring candidates that are at least ``min_distance`` from each other and from those requested before
(``repeats`` allows a pose that many times). ``orchestrator.planner`` decides what a request keeps, and so what
counts: with the pusher redrawn, only the object's state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from orchestrator import protocol
from storage.records import STATE_COLUMN as _COL, Episode


def state_features(shape: str, agent: Sequence[float] | None, obj: Sequence[float],
                   physics: dict[str, float]) -> np.ndarray:
    """The normalised state a diversity distance is measured in.

    Object x, y and agent x, y over WORLD_SIZE; cos and sin of the object's angle; the
    shape one-hot; each physics parameter scaled to [0, 1] over its range. Two shapes
    are always at least sqrt(2) apart, more than any sensible ``min_distance``.
    ``agent`` None: the request redraws the agent, so it does not count (its entries are 0).
    """
    w = protocol.WORLD_SIZE
    ax, ay = (0.0, 0.0) if agent is None else (agent[0] / w, agent[1] / w)
    onehot = [1.0 if shape == s else 0.0 for s in protocol.SHAPES]
    phys = [(float(physics.get(k, d)) - lo) / (hi - lo) for k, (lo, hi, d) in protocol.PHYSICS_RANGES.items()]
    return np.array([obj[0] / w, obj[1] / w, math.cos(obj[2]), math.sin(obj[2]),
                     ax, ay, *onehot, *phys], dtype=np.float64)


@dataclass(frozen=True)
class Candidate:
    """One uncertain state in a new episode."""

    score: float
    episode: Episode
    step: int
    features: np.ndarray


def select_diverse(candidates: Sequence[Candidate], k: int, min_distance: float,
                   taken: Sequence[np.ndarray] = (), max_per_shape: int | None = None,
                   repeats: int = 1) -> list[Candidate]:
    """Greedy by score: keep a candidate only if fewer than ``repeats`` kept ones lie within ``min_distance``
    of it (``repeats`` 1: it is that far from every kept one).

    ``taken`` holds features of states requested earlier, which also count as kept;
    ``max_per_shape`` caps how many kept candidates share an object shape.
    Returns at most ``k`` candidates, highest score first.
    """
    kept: list[Candidate] = []
    per_shape: dict[str, int] = {}
    others = [np.asarray(t) for t in taken]
    for cand in sorted(candidates, key=lambda c: -c.score):
        if len(kept) >= k:
            break
        shape = cand.episode.meta.shape
        if max_per_shape is not None and per_shape.get(shape, 0) >= max_per_shape:
            continue
        if sum(np.linalg.norm(cand.features - o) < min_distance for o in others) < repeats:
            kept.append(cand)
            per_shape[shape] = per_shape.get(shape, 0) + 1
            others.append(cand.features)
    return kept


def episode_features(ep: Episode, step: int, with_agent: bool = True) -> np.ndarray:
    """``state_features`` of ``ep``'s state at ``step`` (its agent left out when ``with_agent`` is False)."""
    s = ep.states[step]
    return state_features(ep.meta.shape, (s[_COL["agent_x"]], s[_COL["agent_y"]]) if with_agent else None,
                          (s[_COL["obj_x"]], s[_COL["obj_y"]], s[_COL["obj_theta"]]), ep.meta.physics)
