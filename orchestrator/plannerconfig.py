"""``ActivePlannerConfig``: the settings of the uncertainty planner (``orchestrator.planner.ActivePlanner``).

Kept apart from the planner so that its many knobs, each with the finding that set its default, do not crowd the
planner's logic; ``orchestrator.planner`` re-exports it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from orchestrator import protocol
from orchestrator.uniform import MIX_POLICIES, UniformPlannerConfig


@dataclass
class ActivePlannerConfig:
    """The uncertainty planner."""

    steps: int = 50
    """Steps per requested episode (after any replayed prefix)."""
    percentile: float = 75.0
    """Adaptive threshold: this percentile of the recent scores of the current model."""
    window: int = 2000
    """How many recent per-step scores the percentile is taken over."""
    budget_per_round: int = 2
    """At most this many requests per planning round (one call of ``plan``)."""
    max_queue_depth: int = 64
    """Never plan past this many queued requests."""
    min_distance: float = 0.15
    """Two requests closer than this in the normalised state space are one too many (see ``repeats``)."""
    repeats: int = 1
    """How many requests may fall within ``min_distance`` of one another (1: each pose once). With the agent
    redrawn, a repeat is the same uncertain object pose pushed from elsewhere: new data, which in a world with a
    rare shape is the most a round can ask of it (``bench loop --repeats``)."""
    memory: int = 256
    """How many recent requests the planner remembers: new candidates keep away from their states, and their
    (episode, step) is not requested again; older ones are forgotten, so a ``serve`` that runs for months holds
    no more (the queue's idempotency key still refuses a step requested before, but not the same pose held at
    the start of the episode collected from it). ``serve`` and ``run`` fill it from the queue's latest requests
    when they start (``ActivePlanner.remember_queue``)."""
    explore_fraction: float = 0.0
    """Share of each round's budget given to uniform requests (0 = pure active)."""
    replay_prefix: bool = False
    """Start from the episode's start and replay actions[:step] instead of starting at the state."""
    at_rest: bool = True
    """Start at the uncertain pose with zero velocities (as uniform and eval episodes start); False keeps the
    state's velocities, but a redrawn agent starts at rest all the same (``redraw_agent``)."""
    task_space_only: bool = True
    """Only request states whose object and agent (where the request keeps it) lie in OBJECT_RANGE /
    AGENT_RANGE: the model is judged there, and an ensemble also disagrees where the data is thin for no
    useful reason (objects pushed against the walls)."""
    redraw_agent: bool = True
    """Keep the uncertain state's object (shape, pose, physics) but draw the agent as a uniform start
    does (away from the object, at rest: the state's pusher velocity belongs to the pusher it replaces):
    starting next to the object, as contact states would, leaves the active arm short of the pusher's free
    motion, which most of the eval error comes from."""
    max_shape_share: float = 0.5
    """At most this share of the requests planned in one call may be of one shape (rounded up, at least 1):
    no collapse onto one shape. Not used with ``shapes_by_progress``, whose quotas take its place."""
    shapes_by_progress: bool = False
    """Split each round's requests over the shapes of ``seed_uniform.shapes`` by what data of each has been
    buying (``orchestrator.shapeprogress``: how much a champion's error on a shape's episodes fell once it
    trained on them, beyond the shape whose error fell least), then pick each shape's states by the score;
    a shape short of candidates (none in the new episodes, or none above the threshold) gets uniform starts
    of that shape. Needs a scorer that gives errors and what its champion trained on
    (``ChampionScorer(with_error=True)``); an experiment, off by default."""
    min_per_shape: int = 0
    """When the planner's own picks (its explore requests included) leave a scored round short, uniform
    starts (reason planner "shape-floor") for the shape with the fewest requests in the round first, until every
    shape of ``seed_uniform.shapes`` has this many or the round is full; its picks count, and the rest of the
    round stays the caller's (its uniform top-up). For callers that plan a round at a time (``bench loop``,
    ``run``'s RoundPlanner), not ``serve``, which plans per upload. 0: off. Not with ``shapes_by_progress``,
    whose quotas take its place."""
    progress_floor: float = 0.25
    """With ``shapes_by_progress``: this share of each round is split equally over the shapes."""
    progress_horizon: int = 1
    """With ``shapes_by_progress``: the horizon of the error whose fall is measured (the scorer's
    ``error_horizon``; 1 is the gate's metric, a longer one weighs the dynamics more)."""
    progress_memory: int = 16
    """With ``shapes_by_progress``: a shape's progress is the mean over its last this many episodes."""
    seed_uniform: UniformPlannerConfig = field(default_factory=UniformPlannerConfig)
    """How seeds (before any model) and exploration requests are drawn; its policy mix is shared."""
    choose_policy: bool = False
    """Also choose each request's collection policy by uncertainty instead of drawing it from the shared
    mix: per policy, the mean disagreement of the recent episodes collected with it (scored by the current
    champion); a policy is drawn with probability ~ score ** ``policy_sharpness``, at least ``policy_floor``."""
    policy_sharpness: float = 4.0
    """Exponent on the policies' scores relative to the best (0: each equally likely; large: greedy)."""
    policy_floor: float = 0.1
    """Least probability of each policy when ``choose_policy`` (exploration), at most 1 / number of policies."""
    policy_window: int = 64
    """How many recent episodes per policy its score is the mean over."""
    within_policy: bool = False
    """Rank each step against the steps of its own collection policy: its score divided by the mean
    score of the recent episodes of that policy (the last ``policy_window`` scored by the current
    champion, these included), so the requests' ``score`` and ``threshold`` are ratios to it. A policy
    that moves more makes every member err more (random waypoints: ~2x the disagreement of a push), but
    a request draws its policy afresh, so what it can buy is the state; an experiment, off by default."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.percentile < 100.0:
            raise ValueError(f"percentile must be in [0, 100), found {self.percentile}")
        if self.window < 1 or self.budget_per_round < 0 or self.max_queue_depth < 1:
            raise ValueError(f"window >= 1, budget_per_round >= 0 and max_queue_depth >= 1 expected, found "
                             f"{self.window}, {self.budget_per_round}, {self.max_queue_depth}")
        if not 0.0 < self.max_shape_share <= 1.0:
            raise ValueError(f"max_shape_share must be in (0, 1], found {self.max_shape_share}")
        if isinstance(self.min_per_shape, bool) or not isinstance(self.min_per_shape, int) or self.min_per_shape < 0:
            raise ValueError(f"min_per_shape must be a whole number of at least 0, found {self.min_per_shape!r}")
        if self.min_per_shape and self.shapes_by_progress:
            raise ValueError("min_per_shape and shapes_by_progress exclude each other: the progress quotas take "
                             f"the floor's place, found min_per_shape={self.min_per_shape}")
        if not 0.0 <= self.progress_floor <= 1.0 or self.progress_memory < 1 or self.progress_horizon < 1:
            raise ValueError(f"progress_floor in [0, 1], progress_memory >= 1 and progress_horizon >= 1 expected, "
                             f"found {self.progress_floor}, {self.progress_memory} and {self.progress_horizon}")
        if isinstance(self.repeats, bool) or not isinstance(self.repeats, int) or self.repeats < 1:
            raise ValueError(f"repeats must be a whole number of at least 1, found {self.repeats!r}")
        if isinstance(self.memory, bool) or not isinstance(self.memory, int) or self.memory < 0:
            raise ValueError(f"memory must be a whole number of at least 0, found {self.memory!r}")
        if self.min_distance < 0 or not 0.0 <= self.explore_fraction <= 1.0:
            raise ValueError(f"min_distance >= 0 and explore_fraction in [0, 1] expected, found "
                             f"{self.min_distance} and {self.explore_fraction}")
        if not protocol.MIN_EPISODE_STEPS <= self.steps <= protocol.MAX_EPISODE_STEPS:
            raise ValueError(f"steps must be in [{protocol.MIN_EPISODE_STEPS}, {protocol.MAX_EPISODE_STEPS}], "
                             f"found {self.steps}")
        if (self.policy_sharpness < 0 or self.policy_window < 1
                or not 0.0 <= self.policy_floor <= 1.0 / len(MIX_POLICIES)):
            raise ValueError(f"policy_sharpness >= 0, policy_window >= 1 and policy_floor in [0, "
                             f"{1.0 / len(MIX_POLICIES)}] expected, found {self.policy_sharpness}, "
                             f"{self.policy_window} and {self.policy_floor}")
