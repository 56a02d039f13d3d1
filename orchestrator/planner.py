"""Planners: where the next episodes should start.

A planner turns newly stored episodes into collection requests. Two share one
interface so every comparison has its control arm:

- ``ActivePlanner`` scores each new episode with the champion ensemble (through a
  ``Scorer`` callable), keeps the steps above an adaptive threshold (a running
  percentile of recent scores), makes them diverse in a normalised state space,
  and caps them by a per-round budget and the queue's depth.
- ``UniformPlanner`` draws start states uniformly over the task space of
  ``orchestrator.protocol``; it is the control arm and the seed of the queue
  before any model exists (``orchestrator.uniform``).

Both draw the collection policy from the same ``PolicyMix``: only where the
episodes start differs between the arms. With ``ActivePlannerConfig.choose_policy``
the active planner also chooses the policy, favouring the one whose recent episodes
the champion disagrees on most (an experiment; off by default).

Where an active request starts: directly at the uncertain state (the object's and the
agent's pose at that step, the episode's shape and physics), at rest, with no action
prefix. Replaying ``actions[:step]`` from the episode's start would reproduce the state
exactly, but the replayed frames repeat data the catalog already holds and make the
episode longer (``collect_episode`` records prefix + steps); starting at the state
spends every collected frame next to the state the model does not understand and keeps
active and uniform episodes the same length, so "per episode" stays a fair unit.
Velocities are zeroed by default because uniform and eval episodes start at rest, and
candidates are kept inside the task space (OBJECT_RANGE / AGENT_RANGE): in ``bench loop``
without these two rules two thirds of the active requests went to one shape, with the
object pushed against a wall (where the ensemble disagrees about the wall's pixels rather
than the dynamics), and the active arm lost clearly on h5; with them it is level on h5
and still about 2% behind uniform on h1. That 2% came from the agent: an uncertain
state usually has the pusher next to the object, so the active arm collected less of the
pusher's free motion, where most of the eval error is. By default (``redraw_agent``)
a request keeps the state's object (shape, pose, physics) and draws the agent as a
uniform start does; with that the arms are level on h1 and h5 (within the seed noise).
``ActivePlannerConfig.replay_prefix`` switches to exact replay.

A redrawn agent is no part of what a request keeps, so it counts neither in the diversity distance
nor in the task-space check: the steps before the pusher reaches the object all hold the object's
start pose, and while the distance counted the source's agent, one pose passed as several states (in
a 48-episode ``bench loop`` arm, 6 to 17 pairs of a round's 16 requests had the very same object). The
distance and the greedy pick are ``orchestrator.diversity``'s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol, Sequence

import numpy as np

from orchestrator import protocol
from orchestrator.diversity import Candidate, episode_features, select_diverse, state_features
from orchestrator.messages import RequestSpec
from orchestrator.plannerconfig import ActivePlannerConfig
from orchestrator.shapeprogress import ShapeProgress
from orchestrator.uniform import MIX_POLICIES, UniformPlanner, agent_away_from
from storage.requests import NewRequest
from storage.records import STATE_COLUMN as _COL, Episode

if TYPE_CHECKING:  # only for type hints: the planner needs no catalog or queue of its own
    from storage.catalog import Catalog
    from storage.queue import RequestQueue

log = logging.getLogger(__name__)


class Planner(Protocol):
    """Turns new episodes into requests (``plan``) and fills an empty queue (``seed``); ``observe`` shows it
    episodes before the champion trains on them, for a caller that retrains before it plans (``bench loop``)."""

    name: str

    def plan(self, new_episodes: Sequence[Episode], limit: int | None = None) -> list[NewRequest]: ...

    def seed(self, n: int, why: str = "seed") -> list[NewRequest]: ...

    def observe(self, episodes: Sequence[Episode]) -> None: ...


@dataclass(frozen=True)
class Scores:
    """What a scorer says about one episode."""

    model_version: str
    """Version of the ensemble that scored it."""
    per_step: np.ndarray
    """(T,) disagreement per step; NaN where a step has no context or no successor."""
    error: np.ndarray | None = None
    """(T,) squared error of the ensemble mean's next frame(s) per step, averaged over the scorer's horizon
    (``uncertainty.score.prediction_error``), when the scorer was asked for it
    (``ChampionScorer(with_error=True)``)."""
    trained: bool | None = None
    """Whether that ensemble was trained on the episode (None: not known)."""


#: Scores an episode with the current champion; None while no model exists.
Scorer = Callable[[Episode], "Scores | None"]


class ActivePlanner:
    """Requests the states the champion ensemble disagrees on most, diverse and budgeted.

    It never looks at episodes ``is_eval`` (``in_eval_split``) says are eval ones: a request from an eval state
    re-enacts that episode (with ``replay_prefix`` step for step, under a seed the catalog's replay check misses)."""

    name = "active"

    def __init__(self, cfg: ActivePlannerConfig, scorer: Scorer, rng: np.random.Generator,
                 queue_depth: Callable[[], int] = lambda: 0,
                 is_eval: Callable[[str], bool] = lambda episode_id: False) -> None:
        self.cfg = cfg
        self.scorer = scorer
        self.rng = rng
        self.queue_depth = queue_depth
        self.is_eval = is_eval
        self.uniform = UniformPlanner(cfg.seed_uniform, rng, queue_depth)
        self._recent: deque[float] = deque(maxlen=cfg.window)
        self._recent_version = ""
        self._requested: deque[np.ndarray] = deque(maxlen=cfg.memory)
        self._requested_steps: deque[tuple[str, int]] = deque(maxlen=cfg.memory)  # in step with _requested
        self.threshold = math.nan
        # per policy, the mean scores of its recent episodes under the current champion (any policy an
        # episode was collected with; choose_policy looks at MIX_POLICIES only)
        self._policy_scores: dict[str, deque[float]] = {}
        self._policy_version = ""
        self.progress = ShapeProgress(cfg.progress_memory)
        self.shape_quotas: dict[str, int] = {}
        """With ``shapes_by_progress``: the last round's requests per shape."""
        self._refused: set[str] = set()  # the RequestSpec fields dropped requests failed (each warned of once)

    def remember_queue(self, queue: RequestQueue, look_back: int = 16) -> None:
        """Take the active requests of ``queue`` last made (as many as the memory holds, of its latest ``look_back``
        times that many: uniform seeds and top-ups are half of ``serve``'s) into the memory of requested states, so a
        service or a run that starts again keeps new candidates away from them: an episode collected at a requested
        pose holds that pose (at rest) while its new pusher approaches, and its idempotency key names another
        episode, so without this the same pose was asked for again after every restart. A request that replays a
        prefix (its start state is its episode's start, not the state asked for) is passed over."""
        latest = sorted(queue.list(limit=look_back * self.cfg.memory), key=lambda r: r.created)
        for r in [r for r in latest if (r.reason or {}).get("planner") == "active"][-self.cfg.memory:]:
            start = r.start_state or {}
            if r.action_prefix or "object" not in start:
                continue
            agent = start.get("agent") if self._keeps_agent() else None
            self._requested.append(state_features(r.shape, agent, start["object"], start.get("physics") or {}))
            self._requested_steps.append((str(r.reason.get("source_episode")), int(r.reason.get("step", -1))))

    def seed(self, n: int, why: str = "seed") -> list[NewRequest]:
        """Uniform requests: before any model exists there is nothing to be uncertain about (and when
        the service tops its queue up, ``why`` = "top-up", its candidates have run out)."""
        room = max(0, self.cfg.max_queue_depth - self.queue_depth())
        return [self.uniform.draw_request(why) for _ in range(min(n, room))]

    def observe(self, episodes: Sequence[Episode]) -> None:
        """With ``shapes_by_progress``, score ``episodes`` before the champion trains on them (their fresh error),
        for a caller that retrains before it plans (``bench loop``); otherwise nothing."""
        if self.cfg.shapes_by_progress:
            for ep in self._collected(episodes):
                scores = self.scorer(ep)
                if scores is not None:
                    self.progress.record(ep, scores)

    def plan(self, new_episodes: Sequence[Episode], limit: int | None = None) -> list[NewRequest]:
        """Score the new episodes and request their most uncertain, mutually distant states.

        With no model yet, each new episode is replaced by one uniform request so the
        queue never runs dry. Returns at most ``budget_per_round`` requests (``limit``, when smaller: a caller
        with less room, whose cut requests would otherwise be remembered as asked) and never more than the room
        left under ``max_queue_depth``. Eval episodes (``is_eval``) are left out.
        """
        room = max(0, self.cfg.max_queue_depth - self.queue_depth())
        budget = min(self.cfg.budget_per_round, room)
        if limit is not None:
            budget = min(budget, max(0, limit))
        new_episodes = self._collected(new_episodes) if budget else []
        if not new_episodes:
            return []
        scored = [(ep, self.scorer(ep)) for ep in new_episodes]
        if any(s is None for _, s in scored):
            return [self.uniform.draw_request("seed") for _ in range(min(budget, len(new_episodes)))]
        scored = self._one_version(scored)
        if self.cfg.choose_policy or self.cfg.within_policy:
            self._update_policy_scores(scored)
        n_explore = int(round(budget * self.cfg.explore_fraction))
        versions = {id(ep): s.model_version for ep, s in scored}
        done = set(self._requested_steps)
        fresh = [c for c in self._candidates(scored) if (c.episode.meta.episode_id, c.step) not in done]
        k = budget - n_explore
        if self.cfg.shapes_by_progress:
            chosen, short = self._by_progress(scored, fresh, k)
        else:
            chosen, short = select_diverse(fresh, k, self.cfg.min_distance, list(self._requested),
                                           max_per_shape=max(1, math.ceil(k * self.cfg.max_shape_share)),
                                           repeats=self.cfg.repeats), {}
        requests = []
        for cand in chosen:
            request = self._request(cand, versions[id(cand.episode)])
            if self._valid(request, cand):  # (one dropped was not requested: it keeps no other state away)
                self._requested.append(cand.features)
                self._requested_steps.append((cand.episode.meta.episode_id, cand.step))
                requests.append(request)
        requests += [self.uniform.draw_request("shape-fill", shape) for shape, n in short.items() for _ in range(n)]
        requests += [self.uniform.draw_request("explore") for _ in range(n_explore)]
        return requests + self._shape_floor(requests, budget)

    def _shape_floor(self, requests: list[NewRequest], budget: int) -> list[NewRequest]:
        """Uniform starts that bring every shape up to ``min_per_shape`` in a round short of ``budget``,
        the shape with the fewest requests first (ties in ``seed_uniform.shapes`` order)."""
        shapes = self.cfg.seed_uniform.shapes
        counts = {shape: sum(r.shape == shape for r in requests) for shape in shapes}
        fill: list[str] = []
        while len(requests) + len(fill) < budget and min(counts.values()) < self.cfg.min_per_shape:
            shape = min(shapes, key=lambda s: counts[s])  # min keeps the first of a tie: the config's order
            counts[shape] += 1
            fill.append(shape)
        return [self.uniform.draw_request("shape-floor", shape) for shape in fill]

    def _collected(self, episodes: Sequence[Episode]) -> list[Episode]:
        """``episodes`` less the eval split's."""
        return [ep for ep in episodes if not self.is_eval(ep.meta.episode_id)]

    def _valid(self, request: NewRequest, cand: Candidate) -> bool:
        """Whether ``request`` passes ``RequestSpec`` (as a worker's grant must): an ingested or older episode's
        state may not (an angle or physics out of bounds); it is dropped then, not left to die. Warned once a field."""
        try:
            RequestSpec(**dataclasses.asdict(request))
            return True
        except protocol.ProtocolError as exc:
            where = exc.message.split(":", 1)[0]  # the field (RequestSpec's: a bounded set)
            said = logging.DEBUG if where in self._refused else logging.WARNING
            log.log(said, "no request for step %d of episode %s: %s (said once per field)", cand.step,
                    protocol.one_line(cand.episode.meta.episode_id), exc.message)
            self._refused.add(where)
            return False

    def _by_progress(self, scored: list[tuple[Episode, Scores]], candidates: list[Candidate],
                k: int) -> tuple[list[Candidate], dict[str, int]]:
        """``k`` candidates split over shapes by ``ShapeProgress.quotas``, and per shape how many it lacks."""
        version = scored[-1][1].model_version
        for ep, s in scored:
            self.progress.record(ep, s)
        knows = any(s.trained is not None for _, s in scored)  # whether this champion can say what it trained on
        for ep in self.progress.waiting(version) if knows else ():  # fresh under an earlier one: seen now?
            again = self.scorer(ep)
            if again is not None and again.model_version == version:
                self.progress.record(ep, again)
        self.shape_quotas = self.progress.quotas(k, self.cfg.seed_uniform.shapes, self.cfg.progress_floor)
        chosen, short = [], {}
        for shape, quota in self.shape_quotas.items():
            picked = select_diverse([c for c in candidates if c.episode.meta.shape == shape], quota,
                                    self.cfg.min_distance, list(self._requested), repeats=self.cfg.repeats)
            chosen += picked
            if quota > len(picked):
                short[shape] = quota - len(picked)
        return sorted(chosen, key=lambda c: -c.score), short

    def _one_version(self, scored: list[tuple[Episode, Scores]]) -> list[tuple[Episode, Scores]]:
        """Scores of one champion only (each lives on its own scale): when a promotion happened while the
        batch was scored, the episodes the old champion scored are scored again by the new one (and
        dropped if yet another promotion beats that)."""
        latest = scored[-1][1].model_version
        if all(s.model_version == latest for _, s in scored):
            return scored
        again = [(ep, s if s.model_version == latest else self.scorer(ep)) for ep, s in scored]
        return [(ep, s) for ep, s in again if s is not None and s.model_version == latest]

    def _candidates(self, scored: list[tuple[Episode, Scores]]) -> list[Candidate]:
        """Update the running threshold with the new scores, then keep the steps above it."""
        version = scored[-1][1].model_version
        if version != self._recent_version:  # a new champion: its scores live on another scale
            self._recent.clear()
            self._recent_version = version
        if self.cfg.within_policy:
            scored = relative_to_policy(scored, self.policy_means())
        for _, s in scored:
            self._recent.extend(float(v) for v in s.per_step if np.isfinite(v))
        if not self._recent:
            return []
        self.threshold = float(np.percentile(np.fromiter(self._recent, float), self.cfg.percentile))
        out = []
        for ep, s in scored:
            for step, value in enumerate(s.per_step):
                if np.isfinite(value) and value > self.threshold and step < len(ep) and self._admissible(ep, step):
                    out.append(Candidate(float(value), ep, step, episode_features(ep, step, self._keeps_agent())))
        return out

    def _keeps_agent(self) -> bool:
        """Whether a request starts with its state's agent (replayed or kept), not a redrawn one."""
        return self.cfg.replay_prefix or not self.cfg.redraw_agent

    def _update_policy_scores(self, scored: list[tuple[Episode, Scores]]) -> None:
        """Each new episode's mean score goes to its policy's recent scores (reset on a new champion)."""
        version = scored[-1][1].model_version
        if version != self._policy_version:  # another champion's scores are on another scale
            self._policy_scores.clear()
            self._policy_version = version
        for ep, s in scored:
            finite = s.per_step[np.isfinite(s.per_step)]
            if finite.size:
                recent = self._policy_scores.setdefault(ep.meta.policy, deque(maxlen=self.cfg.policy_window))
                recent.append(float(finite.mean()))

    def policy_means(self) -> dict[str, float]:
        """Per policy, the mean score of its recent episodes under the current champion (those scored)."""
        return {n: float(np.mean(r)) for n, r in self._policy_scores.items() if r}

    def policy_weights(self) -> dict[str, float]:
        """Probability of each policy for the next active request (the shared mix's while nothing is scored).

        A policy not yet scored under the current champion counts as the best scored one, so it is tried.
        """
        means = {n: m for n, m in self.policy_means().items() if n in MIX_POLICIES}
        if not self.cfg.choose_policy or not means or max(means.values()) <= 0:
            w = self.cfg.seed_uniform.policies.push_weight
            return {"push": w, "random_waypoints": 1.0 - w}
        best = max(means.values())
        raw = np.array([max(means.get(n, best), 0.0) / best for n in MIX_POLICIES]) ** self.cfg.policy_sharpness
        floor = self.cfg.policy_floor
        probs = floor + (1.0 - floor * len(MIX_POLICIES)) * raw / raw.sum()
        return {n: float(p) for n, p in zip(MIX_POLICIES, probs)}

    def _draw_policy(self) -> tuple[str, dict]:
        mix = self.cfg.seed_uniform.policies
        if not self.cfg.choose_policy:
            return mix.draw(self.rng)
        weights = self.policy_weights()
        name = str(self.rng.choice(MIX_POLICIES, p=[weights[n] for n in MIX_POLICIES]))
        return name, mix.params_for(name, self.rng)

    def _admissible(self, ep: Episode, step: int) -> bool:
        if not self.cfg.task_space_only:
            return True
        s = ep.states[step]
        (olo, ohi), (alo, ahi) = protocol.OBJECT_RANGE, protocol.AGENT_RANGE
        agent_in = not self._keeps_agent() or (alo <= s[_COL["agent_x"]] <= ahi and alo <= s[_COL["agent_y"]] <= ahi)
        return olo <= s[_COL["obj_x"]] <= ohi and olo <= s[_COL["obj_y"]] <= ohi and agent_in

    def _request(self, cand: Candidate, model_version: str) -> NewRequest:
        ep, step = cand.episode, cand.step
        policy, params = self._draw_policy()
        if self.cfg.replay_prefix:
            start, prefix = dict(ep.meta.start_state), ep.actions[:step].astype(float).tolist()
        else:
            start, prefix = state_at(ep, step), []
            if self.cfg.at_rest:
                start["agent_vel"], start["object_vel"] = [0.0, 0.0], [0.0, 0.0, 0.0]
            if self.cfg.redraw_agent:  # a new pusher, at rest as a uniform start's: not the old one's speed
                start["agent"], start["agent_vel"] = list(agent_away_from(self.rng, start["object"])), [0.0, 0.0]
        scale = self.threshold if self.threshold > 0 else 1.0
        reason = {"model_version": model_version, "score": cand.score, "source_episode": ep.meta.episode_id,
                  "step": step, "planner": "active", "threshold": self.threshold}
        if self.cfg.within_policy:
            reason["within_policy"] = True  # score and threshold are ratios to the policy's mean
        if self.cfg.shapes_by_progress:
            reason["shape_quotas"] = dict(self.shape_quotas)
        if self.cfg.choose_policy:
            reason["policy_weights"] = {n: round(w, 4) for n, w in self.policy_weights().items()}
        # relative to the threshold, so requests from different champions compare; bounded (a threshold near 0)
        priority = max(-protocol.MAX_PRIORITY, min(round(cand.score / scale, 6), protocol.MAX_PRIORITY))
        return NewRequest(
            task=ep.meta.task, shape=ep.meta.shape, start_state=start,
            policy=policy, policy_params=params, action_prefix=prefix, steps=self.cfg.steps,
            priority=priority, reason=reason, idempotency_key=f"active:{ep.meta.episode_id}:{step}",
        )


def relative_to_policy(scored: Sequence[tuple[Episode, Scores]],
                       means: dict[str, float]) -> list[tuple[Episode, Scores]]:
    """Each episode's scores divided by ``means`` of its policy; an episode whose policy has no positive
    mean there keeps its scores."""
    out = []
    for ep, s in scored:
        mean = means.get(ep.meta.policy, math.nan)
        out.append((ep, Scores(s.model_version, s.per_step / mean) if mean > 0 else s))
    return out


def state_at(ep: Episode, step: int) -> dict:
    """The simulator state (``SimState.to_dict`` form) at ``step`` of an episode."""
    s = ep.states[step]
    return {"shape": ep.meta.shape,
            "agent": [float(s[_COL["agent_x"]]), float(s[_COL["agent_y"]])],
            "agent_vel": [float(s[_COL["agent_vx"]]), float(s[_COL["agent_vy"]])],
            "object": [float(s[_COL["obj_x"]]), float(s[_COL["obj_y"]]), float(s[_COL["obj_theta"]])],
            "object_vel": [float(s[_COL["obj_vx"]]), float(s[_COL["obj_vy"]]), float(s[_COL["obj_omega"]])],
            "physics": {k: float(v) for k, v in ep.meta.physics.items()}}


def in_eval_split(catalog: Catalog) -> Callable[[str], bool]:
    """``ActivePlanner``'s ``is_eval`` from ``catalog``: whether it indexes the episode in the eval split."""
    return lambda episode_id: (row := catalog.find(episode_id)) is not None and row.split == "eval"
