"""Collecting episodes: reset to a start state, replay a prefix, run a policy, record everything.

``collect_episode`` is what a worker does for one collection request (and what
``activecollect collect`` does locally, over a ``collect_plan``); ``create_eval_split`` builds the pinned
evaluation split from a fixed seed. The simulator is deterministic, so an episode is a function of
its metadata (``planned_meta``): ``plan_replays`` tells, before anything is collected, which episodes
of a plan the catalog would refuse as replays of the other split's (``storage.eval_split``).
"""

from __future__ import annotations

import importlib.metadata
import uuid
from datetime import datetime, timezone
from typing import Any, Callable, Mapping

import numpy as np

from orchestrator.protocol import MAX_EPISODE_STEPS, MAX_PREFIX_STEPS, SHAPES, WORLD_SIZE
from storage.errors import CatalogError
from storage.records import ACTION_DIM, STATE_DIM, Episode, EpisodeMeta
from workers.env import CONTROL_HZ, PushSim, SimState, sample_state
from workers.policies import make_policy

#: Task family of every episode this module records.
TASK = "push"
#: Policy and parameters of the evaluation split.
EVAL_POLICY = "push"


class CollectionStopped(Exception):
    """``collect_episode``'s ``stop`` said so before the episode was complete: nothing is returned."""


class EvalSplitConflict(ValueError):
    """An evaluation split is already pinned and was made with other parameters.

    ``held`` and ``asked``: the parameters that differ (keys of ``create_eval_split``'s
    params), as the pinned split has them and as they were asked for; a value the pinned
    split's episodes do not tell (a split pinned without its parameters) is None.
    """

    def __init__(self, message: str, held: dict[str, Any], asked: dict[str, Any]) -> None:
        super().__init__(message)
        self.held = held
        self.asked = asked


def software_version() -> str:
    """The installed activecollect version ('0+unknown' when run from an uninstalled tree)."""
    try:
        return importlib.metadata.version("activecollect")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


def _check_prefix(action_prefix: Any) -> np.ndarray:
    if action_prefix is None:
        return np.zeros((0, ACTION_DIM), np.float32)
    try:
        prefix = np.asarray(action_prefix, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"action_prefix: expected a (P, {ACTION_DIM}) array of numbers") from None
    if prefix.size == 0:
        return np.zeros((0, ACTION_DIM), np.float32)
    if prefix.ndim != 2 or prefix.shape[1] != ACTION_DIM:
        raise ValueError(f"action_prefix: expected shape (P, {ACTION_DIM}), found {prefix.shape}")
    if len(prefix) > MAX_PREFIX_STEPS:
        raise ValueError(f"action_prefix: expected at most {MAX_PREFIX_STEPS} steps, found {len(prefix)}")
    prefix = prefix.astype(np.float32)
    if not (np.isfinite(prefix).all() and (prefix >= 0).all() and (prefix <= WORLD_SIZE).all()):
        raise ValueError(f"action_prefix: expected finite targets in [0, {WORLD_SIZE}]")
    return prefix


def collect_episode(*, start_state: SimState | Mapping[str, Any], policy: str,
                    policy_params: Mapping[str, Any] | None = None, seed: int, steps: int = 50,
                    image_size: int = 64, action_prefix: np.ndarray | None = None,
                    request_id: str = "", worker_id: str = "", model_version: str = "",
                    palette: Mapping[str, tuple[int, int, int]] | None = None,
                    stop: Callable[[], bool] | None = None) -> Episode:
    """Records one episode: reset to ``start_state``, replay ``action_prefix``, then run ``policy``.

    The episode has ``len(action_prefix) + steps`` steps; its leading actions are the prefix
    (``meta.action_prefix_len`` says how many), so the state the prefix leads to is recorded
    along with the context before it. The policy is seeded with ``seed`` and starts at the
    state the prefix leaves. Actions are stored as float32 and the simulator is stepped with
    exactly the stored values, so replaying an episode's actions reproduces it bit for bit.
    ``palette`` recolours the objects (``PushSim``; experiments only: the episode's metadata
    does not record it). ``stop``, asked before each step, abandons the episode when it says True (a worker
    told to stop now: an episode at 1024 px takes tens of seconds).

    Raises ValueError for a bad state, policy, parameters, step count, image size or prefix;
    CollectionStopped when ``stop`` said so.
    """
    state = start_state if isinstance(start_state, SimState) else SimState.from_dict(start_state)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= MAX_EPISODE_STEPS:
        raise ValueError(f"steps: expected an int in [1, {MAX_EPISODE_STEPS}], found {steps!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, found {seed!r}")
    prefix = _check_prefix(action_prefix)
    pol = make_policy(policy, policy_params, np.random.default_rng(int(seed)))
    sim = PushSim(image_size, palette)
    sim.reset(state)

    n_prefix = len(prefix)
    total = n_prefix + int(steps)
    frames = np.empty((total, image_size, image_size, 3), np.uint8)
    actions = np.empty((total, ACTION_DIM), np.float32)
    states = np.empty((total, STATE_DIM), np.float64)
    actions[:n_prefix] = prefix
    for t in range(total):
        if stop is not None and stop():
            raise CollectionStopped(f"stopped after {t} of {total} steps")
        sim.render_into(frames[t])
        sim.state_vector(states[t])
        if t == n_prefix:
            pol.reset(sim)
        if t >= n_prefix:
            actions[t] = pol.act(sim)
        sim.step(float(actions[t, 0]), float(actions[t, 1]))

    meta = _meta(state, policy, pol.params, int(seed), n_prefix, image_size, worker_id=worker_id,
                 request_id=request_id, model_version=model_version)
    return Episode(meta=meta, frames=frames, actions=actions, states=states)


def _meta(state: SimState, policy: str, params: Mapping[str, Any], seed: int, n_prefix: int, image_size: int,
          **who: str) -> EpisodeMeta:
    return EpisodeMeta(
        episode_id=uuid.uuid4().hex, task=TASK, shape=state.shape, physics=dict(state.physics),
        seed=seed, policy=policy, policy_params=dict(params), start_state=state.to_dict(),
        action_prefix_len=n_prefix, image_size=image_size, control_hz=float(CONTROL_HZ),
        software_version=software_version(), created=datetime.now(timezone.utc).isoformat(), **who)


def planned_meta(*, start_state: SimState, policy: str, seed: int, image_size: int = 64) -> EpisodeMeta:
    """The metadata ``collect_episode`` records for these arguments (no prefix, a new id), without simulating.
    Raises ValueError for an unknown policy."""
    return _meta(start_state, policy, make_policy(policy, None, np.random.default_rng(seed)).params, seed, 0,
                 image_size)


def collect_plan(episodes: int, seed: int, shape: str | None = None,
                 random_physics: bool = False) -> list[tuple[int, SimState]]:
    """The (policy seed, start state) of ``episodes`` episodes drawn from ``seed``: of ``shape``, or (None)
    shapes in turn; default physics, or physics drawn uniformly over the task space with ``random_physics``.
    What ``activecollect collect`` and ``create_eval_split`` record: the same arguments, the same episodes."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes: expected a positive int, found {episodes!r}")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(episodes):
        start = sample_state(rng, shape=SHAPES[i % len(SHAPES)] if shape is None else shape,
                             random_physics=random_physics)
        out.append((int(rng.integers(2**31)), start))
    return out


def eval_split_plan(episodes: int = 24, seed: int = 1234, random_physics: bool = False) -> list[tuple[int, SimState]]:
    """The (policy seed, start state) of each evaluation episode: shapes in turn, default physics
    (or physics drawn uniformly over the task space with ``random_physics``)."""
    return collect_plan(episodes, seed, None, random_physics)


def plan_replays(catalog, planned: list[tuple[int, SimState]], policy: str, image_size: int,
                 split: str = "train", within: bool = False) -> dict[int, str]:
    """Which episodes of ``planned`` (``collect_plan``), collected with ``policy`` and indexed in ``split``, the
    catalog would refuse as replays of an episode of the other split: {their index: that episode's id}.
    Collects nothing; the catalog's check when each is indexed stays the one that holds. ``within``: those that
    would record an episode of ``split`` again instead."""
    metas = [planned_meta(start_state=start, policy=policy, seed=seed, image_size=image_size)
             for seed, start in planned]
    found = catalog.replays(split, metas, within=within)
    return {i: found[m.episode_id] for i, m in enumerate(metas) if m.episode_id in found}


def eval_split_params(episodes: int = 24, seed: int = 1234, steps: int = 50, image_size: int = 64,
                      palette: Mapping[str, tuple[int, int, int]] | None = None,
                      random_physics: bool = False) -> dict[str, Any]:
    """The parameters ``create_eval_split`` pins with the split it makes."""
    params: dict[str, Any] = {"episodes": episodes, "seed": seed, "steps": steps, "image_size": image_size,
                              "policy": EVAL_POLICY}
    if palette:
        params["palette"] = {shape: list(rgb) for shape, rgb in sorted(palette.items())}
    if random_physics:
        params["random_physics"] = True
    return params


def check_eval_split(catalog, episodes: int = 24, seed: int = 1234, steps: int = 50, image_size: int = 64,
                     palette: Mapping[str, tuple[int, int, int]] | None = None,
                     random_physics: bool = False) -> str | None:
    """Whether ``create_eval_split`` with these arguments would keep the pinned split: its hash when
    it would, None when none is pinned yet (it would make one). Collects nothing, changes nothing.

    Raises ``EvalSplitConflict`` when a split is pinned that was made with other parameters.
    """
    existing = catalog.eval_split()
    if existing is None:
        return None
    plan = eval_split_plan(episodes, seed, random_physics)
    _check_same_split(catalog, existing, eval_split_params(episodes, seed, steps, image_size, palette,
                                                           random_physics), plan)
    return existing.hash


def create_eval_split(catalog, episodes: int = 24, seed: int = 1234, steps: int = 50,
                      image_size: int = 64, palette: Mapping[str, tuple[int, int, int]] | None = None,
                      random_physics: bool = False) -> str:
    """Collects the evaluation split with the ``push`` policy, indexes it (split "eval"), pins it.

    ``catalog`` is a ``storage.catalog.Catalog``. Shapes take turns, physics are the defaults,
    start states and policy seeds come from ``seed``. Experiments: ``palette`` recolours the
    objects, ``random_physics`` draws each episode's physics uniformly over the task space; both
    are pinned with the other parameters. Returns the split's hash. When a split
    is already pinned, returns its hash if it was made with the same parameters and raises
    ``EvalSplitConflict`` (a ValueError) otherwise (see ``check_eval_split``). Raises ``CatalogError``,
    collecting nothing, when train episodes already record some of the split's (``plan_replays``). Episodes an
    interrupted call indexed (no split is pinned until every one is) are taken up again, not recorded twice.
    """
    plan = eval_split_plan(episodes, seed, random_physics)
    params = eval_split_params(episodes, seed, steps, image_size, palette, random_physics)
    existing = catalog.eval_split()
    if existing is not None:
        _check_same_split(catalog, existing, params, plan)
        return existing.hash
    replayed = plan_replays(catalog, plan, EVAL_POLICY, image_size, split="eval")
    if replayed:  # refused before any is collected, not once some are indexed
        i, train = min(replayed.items())
        raise CatalogError(f"train episode {train} already records evaluation episode {i + 1} of seed {seed} "
                           f"({len(replayed)} of the {episodes} are recorded as train episodes): models trained "
                           "on them would be measured on their own training data; give another seed")
    ids, kept = [], _recorded_already(catalog, plan, steps, image_size, palette)
    for i, (policy_seed, start) in enumerate(plan):
        if i in kept:  # an interrupted create recorded it: resumed, not recorded twice
            ids.append(kept[i])
            continue
        ep = collect_episode(start_state=start, policy=EVAL_POLICY, seed=policy_seed, steps=steps,
                             image_size=image_size, palette=palette)
        ids.append(catalog.add_episode(ep, split="eval").episode_id)
    return catalog.pin_eval_split(ids, params=params)


def _recorded_already(catalog, plan: list[tuple[int, SimState]], steps: int, image_size: int,
                      palette: Mapping[str, tuple[int, int, int]] | None) -> dict[int, str]:
    """The episodes of ``plan`` an earlier, interrupted ``create_eval_split`` indexed (eval episodes not pinned
    yet, of these steps and size, not quarantined, their first frame the one this call renders -- the metadata
    does not record a ``palette``): {their index in ``plan``: their id}."""
    found = plan_replays(catalog, plan, EVAL_POLICY, image_size, split="eval", within=True)
    kept = {}
    for i, episode_id in found.items():
        row = catalog.get(episode_id)
        if row.frames != steps or row.quarantined or catalog.meta(episode_id).image_size != image_size:
            continue
        policy_seed, start = plan[i]
        first = collect_episode(start_state=start, policy=EVAL_POLICY, seed=policy_seed, steps=1,
                                image_size=image_size, palette=palette).frames[0]
        if np.array_equal(catalog.load(episode_id).frames[0], first):
            kept[i] = episode_id
    return kept


def _check_same_split(catalog, existing, params: dict[str, Any], plan: list[tuple[int, SimState]]) -> None:
    """Raises EvalSplitConflict unless the pinned split is the one ``params`` would make."""
    if existing.params:
        if existing.params != params:
            keys = [k for k in dict.fromkeys([*existing.params, *params])
                    if existing.params.get(k) != params.get(k)]
            raise EvalSplitConflict(f"an evaluation split is already pinned with {existing.params}; "
                                    f"asked for {params}", {k: existing.params.get(k) for k in keys},
                                    {k: params.get(k) for k in keys})
        return
    # Pinned without parameters: compare what its episodes' metadata says.
    want = sorted((policy_seed, start.shape) for policy_seed, start in plan)
    found = []
    for episode_id in existing.ids:
        m, frames = catalog.meta(episode_id), catalog.get(episode_id).frames
        held = {k: v for k, v in (("image_size", m.image_size), ("steps", frames), ("policy", m.policy))
                if v != params[k]}
        if held:
            raise EvalSplitConflict(
                f"an evaluation split is already pinned with other parameters: episode {episode_id} has "
                f"{frames} steps at {m.image_size}px by policy {m.policy!r}, asked for {params}",
                held, {k: params[k] for k in held})
        found.append((m.seed, m.shape))
    if sorted(found) != want:
        held = {"episodes": len(found)} if len(found) != params["episodes"] else {"seed": None}
        raise EvalSplitConflict(f"an evaluation split is already pinned whose {len(found)} episodes are "
                                f"not the ones {params} makes", held, {k: params[k] for k in held})
