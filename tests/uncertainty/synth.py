"""Synthetic episodes for the uncertainty tests: a pusher square that moves halfway to its target each step.

Not the simulator: a deterministic toy world (numpy only) whose next frame is
predictable from the frames and the action, built as real ``storage.records.Episode``
objects. ``shape`` changes the look: "T" is the training world; "disk" and "L"
draw other colours and objects, so a model trained on "T" has never seen them.
"""

from __future__ import annotations

import uuid

import numpy as np

from storage.records import STATE_DIM, Episode, EpisodeMeta

WORLD = 512.0
_SHAPE_NO = {"T": 1, "box": 2, "L": 3, "disk": 4}
_LOOK = {  # agent colour, object colour, object half-size (pixels at 16px), round object
    "T": ((230, 40, 40), (40, 40, 220), 2, False),
    "box": ((230, 40, 40), (40, 40, 220), 3, False),
    "L": ((40, 230, 230), (250, 250, 30), 3, False),
    "disk": ((250, 140, 0), (20, 200, 20), 4, True),
}


def _draw(size: int, agent: np.ndarray, obj: np.ndarray, shape: str) -> np.ndarray:
    agent_rgb, obj_rgb, half, rnd = _LOOK[shape]
    scale = size / 16
    img = np.full((size, size, 3), 90, np.uint8)
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    ox, oy = obj / WORLD * size
    r = half * scale
    mask = ((xx - ox) ** 2 + (yy - oy) ** 2 <= r * r) if rnd else ((abs(xx - ox) <= r) & (abs(yy - oy) <= r))
    img[mask] = obj_rgb
    ax, ay = agent / WORLD * size
    blob = np.exp(-((xx - ax) ** 2 + (yy - ay) ** 2) / (2 * (1.5 * scale) ** 2))[..., None]  # (H, W, 1)
    return np.round(img * (1 - blob) + np.asarray(agent_rgb) * blob).astype(np.uint8)


def make_episode(seed: int, shape: str = "T", steps: int = 12, size: int = 16) -> Episode:
    """A toy episode: the pusher moves halfway to each target action; the object stays put."""
    rng = np.random.default_rng(seed)
    agent = rng.uniform(100, 412, size=2)
    obj = rng.uniform(150, 362, size=2)
    frames, actions, states = [], [], []
    start = {"shape": shape, "agent": agent.tolist(), "agent_vel": [0.0, 0.0],
             "object": [*obj.tolist(), 0.0], "object_vel": [0.0, 0.0, 0.0],
             "physics": {"mass": 1.0, "friction": 0.6, "ground_friction": 1.0}}
    vel = np.zeros(2)
    for _ in range(steps):
        frames.append(_draw(size, agent, obj, shape))
        target = np.clip(agent + rng.normal(0, 60, size=2), 40, 472)
        actions.append(target)
        row = np.zeros(STATE_DIM)
        row[0:2], row[2:4], row[4:6] = agent, vel, obj
        states.append(row)
        new = agent + 0.5 * (target - agent)
        vel, agent = new - agent, new
    meta = EpisodeMeta(episode_id=uuid.UUID(int=seed + _SHAPE_NO[shape] * 10**6).hex, task="push",
                       shape=shape, physics=dict(start["physics"]), seed=seed, policy="random_waypoints",
                       start_state=start, image_size=size)
    return Episode(meta, np.stack(frames), np.asarray(actions, np.float32), np.asarray(states))
