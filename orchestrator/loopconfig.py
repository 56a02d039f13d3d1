"""The closed loop's configurations: ``RunConfig`` (``activecollect run``) and
``LoopBenchConfig`` (``activecollect bench loop``).

Free of torch, so the CLI builds its parsers from these defaults without loading the
models; ``orchestrator.loop`` and ``orchestrator.loopbench`` run them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from orchestrator import protocol
from orchestrator.planner import ActivePlannerConfig
from orchestrator.uniform import PolicyMix, UniformPlannerConfig
from storage.records import TRAINABLE_SIZES, trainable_size
from uncertainty.config import TrainConfig


@dataclass
class RunConfig:
    """``activecollect run``: the whole loop on one machine (defaults finish in minutes on 2 CPU cores)."""

    data_dir: Path
    """Data directory (resumed when it already holds a catalog)."""
    budget: int = 96
    """Stop once the catalog holds this many training episodes."""
    round_episodes: int = 24
    """Retrain after every this many episodes; the next round is planned by the model it made."""
    workers: int = 2
    """Worker processes over Zenoh on loopback."""
    planner: str = "active"
    """``active`` (ensemble disagreement) or ``uniform`` (the control arm)."""
    steps: int = 40
    """Steps per episode."""
    image_size: int = 32
    """Frame size in pixels (workers render at this size)."""
    eval_episodes: int = 16
    """Episodes in the eval split (push policy, all shapes), made when missing."""
    eval_seed: int = 1234
    """Seed of the eval split."""
    seed: int = 0
    """Seeds the planner."""
    retrain_args: tuple[str, ...] = ("--members", "4", "--epochs", "6", "--widths", "8,16,32", "--max-windows",
                                     "1200", "--from-champion", "--device", "cpu", "--min-improvement", "0.005")
    """Arguments of each ``activecollect retrain`` job."""
    retrain_timeout_s: float = 600.0
    """A retrain running longer is killed (the champion stays)."""
    dashboard_port: int = 8765
    """Dashboard port on 127.0.0.1 (0 = any free port, -1 = no dashboard)."""
    namespace: str = "activecollect"
    """Zenoh key prefix."""
    zenoh_port: int = 0
    """Loopback TCP port of the service (0 = a free one)."""
    lease_s: float = 30.0
    """Lease length handed to workers."""
    progress: bool = True
    """Show the live progress line."""

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir)
        if self.planner not in ("active", "uniform"):
            raise ValueError(f"planner must be active or uniform, found {self.planner!r}")
        for name in ("budget", "round_episodes", "workers", "steps", "eval_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, found {getattr(self, name)}")
        if not trainable_size(self.image_size):
            raise ValueError(f"image_size must be {TRAINABLE_SIZES}, found {self.image_size}")
        if self.dashboard_port < -1 or self.dashboard_port > 65535:
            raise ValueError(f"dashboard_port must be -1 (off), 0 (any) or a port, found {self.dashboard_port}")
        if not 0 <= self.zenoh_port <= 65535:
            raise ValueError(f"zenoh_port must be 0 (any) or a port, found {self.zenoh_port}")
        for name in ("lease_s", "retrain_timeout_s"):
            if not getattr(self, name) > 0:  # (NaN too)
                raise ValueError(f"{name} must be > 0, found {getattr(self, name)}")


#: What the active arm ranks steps by: ``disagreement`` (variance over all pixels, as the service's
#: scorer), ``change`` (variance over the pixels that change), ``object`` (``change`` on the steps
#: where the object moves, i.e. the pusher is in contact; other steps are not candidates),
#: ``object_pixels`` (variance over the pixels of the object's colours only: the pusher's own motion,
#: which the policy decides and a start state cannot buy, left out), ``random`` (a random number per
#: step, the same in every run: the planner's threshold, diversity and shape cap without any model
#: score, the ablation that tells what the score itself adds), ``error`` (the champion's actual error on the
#: recorded frames: where the model was wrong, known once an episode is in; the bound on what a perfectly
#: calibrated uncertainty could rank), ``predicted`` (the error the members predict for themselves, with
#: ``--variance-head``), ``total`` (``predicted`` plus the disagreement: the total predictive variance).
SIGNALS = ("disagreement", "change", "object", "object_pixels", "random", "error", "predicted", "total")
#: The signals taken from the members' variance head (horizon 1 only; training needs ``variance_head``).
HEAD_SIGNALS = ("predicted", "total")
#: The objects' colours in ``bench loop``: all alike (the service's world) or one per shape
#: (``workers.env.SHAPE_PALETTE``).
PALETTES = ("uniform", "per-shape")


@dataclass
class LoopBenchConfig:
    """One comparison of the two planners."""

    seeds: tuple[int, ...] = (0, 1, 2)
    """One run of each arm per seed."""
    budget: int = 48
    """Training episodes per arm."""
    round_episodes: int = 16
    """Retrain after every this many episodes (the first round is the uniform seed)."""
    steps: int = 40
    """Steps per episode."""
    image_size: int = 16
    """Frame size in pixels (16: three seeds of both arms at 48 episodes take 1-7 min on a 2-core CPU)."""
    eval_episodes: int = 16
    """Episodes in the eval split (push policy, all shapes)."""
    eval_seed: int = 1234
    """Seed of the eval split (the same for every seed and arm)."""
    train: TrainConfig = field(default_factory=lambda: TrainConfig(
        members=4, epochs=6, batch_size=32, widths=(8, 16, 32), device="cpu", progress=False,
        min_rel_improvement=0.0))
    """Training settings (every retrain trains from scratch on all data so far)."""
    active: ActivePlannerConfig = field(default_factory=lambda: ActivePlannerConfig(
        budget_per_round=16, max_queue_depth=16, percentile=75.0, min_distance=0.15))
    """The active arm's planner (its budget per round is set to ``round_episodes``)."""
    policies: PolicyMix = field(default_factory=PolicyMix)
    """The collection policies of both arms."""
    signal: str = "disagreement"
    """What the active arm ranks steps by (one of ``SIGNALS``)."""
    signal_horizon: int = 1
    """Prediction horizon of the signal."""
    active_policy: bool = False
    """The active arm also chooses each request's collection policy by its episodes' disagreement
    (``ActivePlannerConfig.choose_policy``); the uniform arm keeps the mix."""
    within_policy: bool = False
    """The active arm ranks each step against the steps of its own policy
    (``ActivePlannerConfig.within_policy``)."""
    random_physics: bool = False
    """Physics (mass, friction, ground friction) are part of the task space: the uniform arm, the seed
    rounds and the eval split draw them uniformly over ``protocol.PHYSICS_RANGES`` (the active arm keeps
    an uncertain state's physics, as it keeps its shape); off, every episode has the default physics."""
    shape_weights: tuple[float, ...] = ()
    """The uniform arm, the seed rounds and the uniform requests that fill an active round the planner left
    short draw shapes with these relative weights (one per ``protocol.SHAPES``, in its order) while the
    eval split keeps every shape equally: a fleet's usual task mix that differs from what its model is
    judged on. Empty: every shape equally likely."""
    shapes_by_progress: bool = False
    """The active arm splits each round over shapes by how much training on a shape's episodes lowered the
    champion's error on them (``ActivePlannerConfig.shapes_by_progress``) instead of capping shapes."""
    palette: str = "uniform"
    """The objects' colours (one of ``PALETTES``), in both arms and the eval split: ``per-shape`` makes the
    shapes look different (where a model trained on one shape does not yet know the others)."""
    deterministic: bool = False
    """Each arm's torch takes only deterministic algorithms (``champion.make_torch_deterministic``), so that two
    runs of one configuration give the same figures on a GPU as they do on the CPU, at some speed."""

    def __post_init__(self) -> None:
        if not self.seeds:
            raise ValueError("seeds must name at least one seed")
        if self.round_episodes < 1 or self.budget < 2 * self.round_episodes:
            raise ValueError(f"need round_episodes >= 1 and budget >= 2 rounds, found round_episodes="
                             f"{self.round_episodes}, budget={self.budget}")
        if not trainable_size(self.image_size):
            raise ValueError(f"image_size must be {TRAINABLE_SIZES}, found {self.image_size}")
        if self.signal not in SIGNALS or self.signal_horizon < 1:
            raise ValueError(f"signal must be one of {SIGNALS} and signal_horizon >= 1, found "
                             f"{self.signal!r} and {self.signal_horizon}")
        if self.signal in HEAD_SIGNALS and not self.train.variance_head:
            raise ValueError(f"signal {self.signal} ranks by a variance head: it needs variance_head")
        if self.signal in HEAD_SIGNALS and self.signal_horizon != 1:
            raise ValueError(f"signal {self.signal} ranks by a variance head's next-frame variance: it needs "
                             f"signal_horizon 1, found {self.signal_horizon}")
        if self.shapes_by_progress and self.active.progress_horizon > self.steps - self.train.context:
            raise ValueError(f"progress_horizon must be at most {self.steps - self.train.context} (the steps of an "
                             f"episode less the model's {self.train.context} context frames: no step has a longer "
                             f"error), found {self.active.progress_horizon}")
        if self.palette not in PALETTES:
            raise ValueError(f"palette must be one of {PALETTES}, found {self.palette!r}")
        self.shape_weights = tuple(float(w) for w in self.shape_weights)
        self.active.budget_per_round = self.round_episodes
        self.active.max_queue_depth = self.round_episodes
        self.active.steps = self.steps
        self.active.choose_policy = self.active_policy
        self.active.within_policy = self.within_policy
        self.active.shapes_by_progress = self.shapes_by_progress
        self.active.seed_uniform = self.uniform_config()
        self.active.__post_init__()  # checked again with what this config set (min_per_shape with shapes_by_progress)

    def uniform_config(self) -> UniformPlannerConfig:
        """The uniform arm's planner (and the seed rounds of both arms)."""
        return UniformPlannerConfig(steps=self.steps, max_queue_depth=self.round_episodes, policies=self.policies,
                                    sample_physics=self.random_physics, shapes=protocol.SHAPES,
                                    shape_weights=self.shape_weights)

    def to_json(self) -> dict:
        d = asdict(self)
        d["train"] = self.train.to_dict()
        return d
