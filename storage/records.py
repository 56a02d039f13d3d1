"""Episode records: the in-memory form of one collected episode, shared by the
simulator (which produces it), the MCAP layer (which stores it) and the models
(which learn from it).

Alignment: ``frames[t]`` and ``states[t]`` are observed *before* ``actions[t]``
is applied; the world model learns ``frames[t-C+1..t], actions[t] -> frames[t+1]``.
The last action therefore has no recorded successor frame.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from storage.errors import EpisodeError

#: Column names of ``Episode.states`` (world units: the table is 512 x 512, y up).
STATE_FIELDS: tuple[str, ...] = (
    "agent_x", "agent_y", "agent_vx", "agent_vy",
    "obj_x", "obj_y", "obj_theta", "obj_vx", "obj_vy", "obj_omega",
    "contact",
)
#: The column of each of STATE_FIELDS in an episode's ``states`` array.
STATE_COLUMN: dict[str, int] = {name: i for i, name in enumerate(STATE_FIELDS)}
STATE_DIM = len(STATE_FIELDS)
ACTION_DIM = 2


#: Frame sizes an episode may have: what the simulator renders and workers record (the wire layer's
#: orchestrator.protocol holds the same limits; storage imports nothing above it, a test keeps them equal).
MIN_FRAME_SIZE, MAX_FRAME_SIZE = 8, 1024
#: The smallest frame a model trains and is evaluated on: the predictor takes multiples of 8 (it halves a
#: frame three times; ``uncertainty.model.PredictorConfig``, which imports nothing of storage: a test
#: keeps the two in step) and SSIM needs an 11-pixel window (``uncertainty.metrics``).
MIN_TRAINABLE_SIZE = 16
#: ``trainable_size`` in words, for messages and ``--help``.
TRAINABLE_SIZES = f"a multiple of 8 from {MIN_TRAINABLE_SIZE} to {MAX_FRAME_SIZE}"
#: An episode's metadata, encoded: far more than any request's start state and policy parameters (the
#: wire contract allows 16 KiB each), small enough that a catalog row stays small.
MAX_META_BYTES = 64 * 1024
#: Characters in one string field of the metadata (ids, names, versions, times).
MAX_META_CHARS = 256


def trainable_size(size: int) -> bool:
    """Whether a model trains on ``size``-pixel frames (``TRAINABLE_SIZES``). A catalog's first episode
    fixes the frame size of every later one, so what records or accepts it checks this."""
    return (isinstance(size, int) and not isinstance(size, bool)
            and MIN_TRAINABLE_SIZE <= size <= MAX_FRAME_SIZE and size % 8 == 0)


def _refuse_constant(name: str) -> None:
    raise EpisodeError(f"episode metadata holds {name}; expected finite numbers")


@dataclass
class EpisodeMeta:
    """Provenance of one episode; stored as the MCAP metadata record ``episode``."""

    episode_id: str
    """Globally unique id (uuid4 hex)."""
    task: str
    """Task family, e.g. ``push``."""
    shape: str
    """Pushed object's shape: ``T``, ``box``, ``L`` or ``disk``."""
    physics: dict[str, float]
    """Physics parameters: mass, friction, ground_friction."""
    seed: int
    """Seed of the collection policy's generator."""
    policy: str
    """Collection policy name (``random_waypoints``, ``push``, ...)."""
    policy_params: dict[str, Any] = field(default_factory=dict)
    """Parameters the policy was built with."""
    start_state: dict[str, Any] = field(default_factory=dict)
    """The simulator state the episode was reset to (``workers.env.SimState.to_dict``)."""
    action_prefix_len: int = 0
    """How many of the leading actions replayed a requested prefix."""
    image_size: int = 64
    """Frame height and width in pixels."""
    control_hz: float = 10.0
    """Actions per simulated second."""
    worker_id: str = ""
    """Worker that collected it ('' for local collection)."""
    request_id: str = ""
    """Collection request it fulfils ('' when none)."""
    model_version: str = ""
    """Model version whose disagreement asked for it ('' when none)."""
    software_version: str = ""
    """activecollect version that wrote it."""
    created: str = ""
    """Creation time, ISO 8601 UTC."""

    def to_json(self) -> str:
        """Strict JSON (no NaN or Infinity: the catalog stores it in a JSON column). Raises
        ``EpisodeError`` for a value JSON cannot hold."""
        try:
            return json.dumps(dataclasses.asdict(self), sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise EpisodeError(f"episode metadata of {self.episode_id!r:.80} is not strict JSON: {exc}") from exc

    @classmethod
    def from_json(cls, text: str | bytes) -> "EpisodeMeta":
        """Parse and validate; raises ``EpisodeError`` naming the bad field."""
        if len(text) > MAX_META_BYTES:
            raise EpisodeError(f"episode metadata: expected at most {MAX_META_BYTES} bytes, found {len(text)}")
        try:
            raw = json.loads(text, parse_constant=_refuse_constant)
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise EpisodeError(f"episode metadata is not JSON: {exc}") from exc
        if not isinstance(raw, dict):
            raise EpisodeError(f"episode metadata must be an object, found {type(raw).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        required = {f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
        missing = required - raw.keys()
        if missing:
            raise EpisodeError(f"episode metadata lacks {sorted(missing)}")
        return cls(**{k: v for k, v in raw.items() if k in known})


@dataclass
class Episode:
    """One episode: frames (T,H,W,3) uint8, actions (T,2) float32, states (T,STATE_DIM) float64."""

    meta: EpisodeMeta
    frames: np.ndarray
    actions: np.ndarray
    states: np.ndarray

    def __post_init__(self) -> None:
        t = len(self.frames)
        if self.frames.ndim != 4 or self.frames.shape[-1] != 3 or self.frames.dtype != np.uint8:
            raise EpisodeError(f"frames must be (T,H,W,3) uint8, found {self.frames.shape} {self.frames.dtype}")
        if self.actions.shape != (t, ACTION_DIM):
            raise EpisodeError(f"actions must be ({t}, {ACTION_DIM}), found {self.actions.shape}")
        if self.states.shape != (t, STATE_DIM):
            raise EpisodeError(f"states must be ({t}, {STATE_DIM}), found {self.states.shape}")

    def __len__(self) -> int:
        return len(self.frames)
