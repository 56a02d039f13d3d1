"""The control arm: start states drawn uniformly over the task space, and the collection policies both arms draw.

``UniformPlanner`` is the control arm of every comparison and the seed of the queue before any model
exists; ``PolicyMix`` is the policy mix both arms share (only where the episodes start differs between
them). They were part of ``orchestrator.planner``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from orchestrator import protocol
from storage.records import Episode
from storage.requests import NewRequest

#: Push sides the "push" policy may be given.
PUSH_SIDES: tuple[str, ...] = ("left", "right", "top", "bottom")
#: The policies a ``PolicyMix`` draws from (and an active planner that chooses the policy chooses among).
MIX_POLICIES: tuple[str, ...] = ("push", "random_waypoints")
#: Clearance (world units) between a sampled agent and the object's centre: the largest shape's
#: bounding radius (the L, ~124) plus the agent's (15), so a uniform start never overlaps the object.
AGENT_CLEARANCE = 140.0


@dataclass
class PolicyMix:
    """The collection policies both arms draw from, with their weights."""

    push_weight: float = 0.5
    """Probability of the ``push`` policy (towards a random side); the rest is ``random_waypoints``."""
    push_noise: float = 6.0
    """Noise of the push policy's targets, world units (the policy's own default)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.push_weight <= 1.0:
            raise ValueError(f"push_weight must be in [0, 1], found {self.push_weight}")
        if self.push_noise < 0:
            raise ValueError(f"push_noise must be >= 0, found {self.push_noise}")

    def draw(self, rng: np.random.Generator) -> tuple[str, dict]:
        """One (policy name, params) pair."""
        name = "push" if rng.random() < self.push_weight else "random_waypoints"
        return name, self.params_for(name, rng)

    def params_for(self, name: str, rng: np.random.Generator) -> dict:
        """The params this mix gives policy ``name`` (a push draws its side); raises ValueError if unknown."""
        if name == "push":
            return {"side": str(rng.choice(PUSH_SIDES)), "noise": self.push_noise}
        if name == "random_waypoints":
            return {}
        raise ValueError(f"policy must be one of {MIX_POLICIES}, found {name!r}")


@dataclass
class UniformPlannerConfig:
    """The control arm: uniform start states."""

    steps: int = 50
    """Steps per requested episode."""
    per_episode: int = 1
    """Requests planned per new episode (1 keeps the queue as deep as it was)."""
    max_queue_depth: int = 64
    """Never plan past this many queued requests."""
    sample_physics: bool = False
    """Draw physics uniformly from PHYSICS_RANGES; False uses each parameter's default."""
    shapes: tuple[str, ...] = protocol.SHAPES
    """Shapes to draw from."""
    shape_weights: tuple[float, ...] = ()
    """Relative weight of each of ``shapes`` (same order); empty: each equally likely. A fleet's usual
    task mix is seldom the one its model is judged on (``bench loop --shape-weights``)."""
    policies: PolicyMix = field(default_factory=PolicyMix)
    """Collection policy mix (shared with the active arm)."""

    def __post_init__(self) -> None:
        if not protocol.MIN_EPISODE_STEPS <= self.steps <= protocol.MAX_EPISODE_STEPS:
            raise ValueError(f"steps must be in [{protocol.MIN_EPISODE_STEPS}, {protocol.MAX_EPISODE_STEPS}], "
                             f"found {self.steps}")
        if self.per_episode < 0 or self.max_queue_depth < 1:
            raise ValueError(f"per_episode must be >= 0 and max_queue_depth >= 1, "
                             f"found {self.per_episode} and {self.max_queue_depth}")
        unknown = set(self.shapes) - set(protocol.SHAPES)
        if not self.shapes or unknown:
            raise ValueError(f"shapes must be a non-empty subset of {protocol.SHAPES}, found {self.shapes}")
        if self.shape_weights and (len(self.shape_weights) != len(self.shapes)
                                   or not all(math.isfinite(w) and w >= 0 for w in self.shape_weights)
                                   or not 0 < sum(self.shape_weights) < math.inf):
            raise ValueError(f"shape_weights must be one finite weight >= 0 per shape of {self.shapes}, not all 0, "
                             f"with a finite sum, found {self.shape_weights}")

    def draw_shape(self, rng: np.random.Generator) -> str:
        """One shape, by ``shape_weights`` when given."""
        if not self.shape_weights:
            return str(rng.choice(self.shapes))  # (as before weights: the same draws for a seed)
        w = np.asarray(self.shape_weights, dtype=np.float64)
        return str(rng.choice(self.shapes, p=w / w.sum()))


def uniform_start_state(rng: np.random.Generator, shape: str, sample_physics: bool = False) -> dict:
    """A start state (``SimState.to_dict`` form) drawn uniformly over the task space."""
    lo, hi = protocol.OBJECT_RANGE
    obj = (float(rng.uniform(lo, hi)), float(rng.uniform(lo, hi)), float(rng.uniform(0.0, 2 * math.pi)))
    agent = agent_away_from(rng, obj)
    if sample_physics:
        physics = {k: float(rng.uniform(low, high)) for k, (low, high, _) in protocol.PHYSICS_RANGES.items()}
    else:
        physics = {k: float(default) for k, (_, _, default) in protocol.PHYSICS_RANGES.items()}
    return {"shape": shape, "agent": list(agent), "agent_vel": [0.0, 0.0],
            "object": list(obj), "object_vel": [0.0, 0.0, 0.0], "physics": physics}


def agent_away_from(rng: np.random.Generator, obj: Sequence[float]) -> tuple[float, float]:
    """An agent position drawn uniformly over AGENT_RANGE, at least AGENT_CLEARANCE from the object."""
    alo, ahi = protocol.AGENT_RANGE
    while True:  # rejection sampling; the free area is most of the table
        agent = (float(rng.uniform(alo, ahi)), float(rng.uniform(alo, ahi)))
        if math.hypot(agent[0] - obj[0], agent[1] - obj[1]) >= AGENT_CLEARANCE:
            return agent


class UniformPlanner:
    """Start states drawn uniformly over the task space: the control arm."""

    name = "uniform"

    def __init__(self, cfg: UniformPlannerConfig, rng: np.random.Generator,
                 queue_depth: Callable[[], int] = lambda: 0) -> None:
        self.cfg = cfg
        self.rng = rng
        self.queue_depth = queue_depth

    def seed(self, n: int, why: str = "seed") -> list[NewRequest]:
        """``n`` uniform requests (capped by the queue depth); ``why`` names them in their reason."""
        room = max(0, self.cfg.max_queue_depth - self.queue_depth())
        return [self.draw_request(why) for _ in range(min(n, room))]

    def plan(self, new_episodes: Sequence[Episode], limit: int | None = None) -> list[NewRequest]:
        """``per_episode`` uniform requests per new episode, capped by the queue depth (and by ``limit``)."""
        room = max(0, self.cfg.max_queue_depth - self.queue_depth())
        room = room if limit is None else min(room, max(0, limit))
        return [self.draw_request("uniform") for _ in range(min(room, self.cfg.per_episode * len(new_episodes)))]

    def observe(self, episodes: Sequence[Episode]) -> None:
        """Nothing: where a uniform request starts does not depend on what was collected."""

    def draw_request(self, why: str, shape: str | None = None) -> NewRequest:
        """One uniform request (of ``shape``, else drawn by the config); ``why`` goes into its reason as the
        planner name."""
        shape = shape if shape is not None else self.cfg.draw_shape(self.rng)
        policy, params = self.cfg.policies.draw(self.rng)
        return NewRequest(
            task="push", shape=shape,
            start_state=uniform_start_state(self.rng, shape, self.cfg.sample_physics),
            policy=policy, policy_params=params, action_prefix=[], steps=self.cfg.steps,
            priority=0.0,
            reason={"model_version": "", "score": None, "source_episode": "", "step": None,
                    "planner": why},
        )
