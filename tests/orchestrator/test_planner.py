"""The planners: uniform sampling within the task space, the adaptive threshold, diversity, caps."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from orchestrator import protocol
from orchestrator.loop import RoundPlanner
from orchestrator.diversity import Candidate, select_diverse, state_features
from orchestrator.planner import ActivePlanner, ActivePlannerConfig, Scores, relative_to_policy, state_at
from orchestrator.uniform import AGENT_CLEARANCE, MIX_POLICIES, PolicyMix, UniformPlanner, UniformPlannerConfig
from storage.queue import RequestQueue
from storage.requests import NewRequest
from storage.records import STATE_FIELDS, Episode, EpisodeMeta
from uncertainty.ensemble import Ensemble
from uncertainty.model import PredictorConfig

COL = {n: i for i, n in enumerate(STATE_FIELDS)}


def make_episode(rng: np.random.Generator, steps: int = 20, shape: str = "T", size: int = 16,
                 jitter: float = 60.0) -> Episode:
    """A synthetic episode whose object wanders from a random start (so steps differ in state), within the world
    (as the walls keep a real one), with its first state as its start state."""
    states = np.zeros((steps, len(STATE_FIELDS)))
    start = rng.uniform(150, 350, size=4)
    walk = np.cumsum(rng.normal(0, jitter / math.sqrt(steps), size=(steps, 4)), axis=0)
    pos = np.clip(start + walk, 0.0, protocol.WORLD_SIZE)
    states[:, COL["obj_x"]], states[:, COL["obj_y"]] = pos[:, 0], pos[:, 1]
    states[:, COL["agent_x"]], states[:, COL["agent_y"]] = pos[:, 2], pos[:, 3]
    states[:, COL["obj_theta"]] = np.linspace(0, 1.5 * jitter / 60.0, steps)
    physics = {"mass": 1.0, "friction": 0.6, "ground_friction": 1.0}
    start_state = {"shape": shape, "agent": pos[0, 2:].tolist(), "object": [*pos[0, :2].tolist(), 0.0],
                   "physics": physics}
    meta = EpisodeMeta(episode_id=f"ep{rng.integers(1 << 40):x}", task="push", shape=shape, physics=physics,
                       seed=0, policy="push", start_state=start_state, image_size=size)
    frames = rng.integers(0, 255, size=(steps, size, size, 3), dtype=np.uint8)
    actions = rng.uniform(0, 512, size=(steps, 2)).astype(np.float32)
    return Episode(meta=meta, frames=frames, actions=actions, states=states)


def acfg(**kw) -> ActivePlannerConfig:
    """The active config with the task-space filter and the shape cap off (synthetic episodes are all T)."""
    return ActivePlannerConfig(**{"task_space_only": False, "max_shape_share": 1.0, **kw})


def step_scorer(version: str = "m1"):
    """A real scorer whose per-step score is the step index (so the ranking is known)."""
    return lambda ep: Scores(version, np.arange(len(ep), dtype=float))


def test_uniform_requests_stay_in_the_task_space():
    planner = UniformPlanner(UniformPlannerConfig(sample_physics=True, max_queue_depth=1000),
                             np.random.default_rng(0))
    reqs = planner.seed(400)
    assert len(reqs) == 400
    lo, hi = protocol.OBJECT_RANGE
    alo, ahi = protocol.AGENT_RANGE
    for r in reqs:
        s = r.start_state
        assert r.shape == s["shape"] and r.shape in protocol.SHAPES
        assert lo <= s["object"][0] <= hi and lo <= s["object"][1] <= hi and 0 <= s["object"][2] < 2 * math.pi
        assert alo <= s["agent"][0] <= ahi and alo <= s["agent"][1] <= ahi
        assert math.dist(s["agent"], s["object"][:2]) >= 140.0
        for k, (plo, phi, _) in protocol.PHYSICS_RANGES.items():
            assert plo <= s["physics"][k] <= phi
        assert r.policy in protocol.POLICIES and r.action_prefix == []
        assert r.reason["planner"] == "seed"
    # uniform: every shape and both policies show up about as often as they should
    shapes = [r.shape for r in reqs]
    assert {shapes.count(s) for s in protocol.SHAPES} <= set(range(70, 131))
    xs = np.array([r.start_state["object"][0] for r in reqs])
    assert abs(xs.mean() - (lo + hi) / 2) < 15 and xs.std() > (hi - lo) / 4
    pushes = sum(r.policy == "push" for r in reqs)
    assert 150 < pushes < 250


def test_shape_weights_skew_the_uniform_draw_and_are_checked():
    cfg = UniformPlannerConfig(max_queue_depth=1000, shape_weights=(6.0, 2.0, 0.0, 2.0))  # T, box, L, disk
    shapes = [r.shape for r in UniformPlanner(cfg, np.random.default_rng(0)).seed(1000)]
    assert shapes.count("L") == 0
    assert 540 < shapes.count("T") < 660 and 150 < shapes.count("box") < 250 and 150 < shapes.count("disk") < 250
    # Without weights the draws are those from before weights existed (the same shapes for a seed).
    rng = np.random.default_rng(3)
    plain = [UniformPlannerConfig().draw_shape(rng) for _ in range(50)]
    rng = np.random.default_rng(3)
    assert plain == [str(rng.choice(protocol.SHAPES)) for _ in range(50)]
    for bad in ((1.0, 1.0), (1.0, -1.0, 1.0, 1.0), (math.nan, 1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0),
                (1e308, 1e308, 0.0, 0.0)):
        with pytest.raises(ValueError, match="shape_weights must be one finite weight >= 0 per shape"):
            UniformPlannerConfig(shape_weights=bad)


def test_same_seed_gives_same_requests():
    a = UniformPlanner(UniformPlannerConfig(), np.random.default_rng(7)).seed(5)
    b = UniformPlanner(UniformPlannerConfig(), np.random.default_rng(7)).seed(5)
    assert [r.start_state for r in a] == [r.start_state for r in b]
    assert [r.policy_params for r in a] == [r.policy_params for r in b]


def test_active_planner_seeds_uniform_before_any_model():
    rng = np.random.default_rng(1)
    planner = ActivePlanner(acfg(), lambda ep: None, rng)
    assert [r.reason["planner"] for r in planner.seed(3)] == ["seed"] * 3
    # with no champion, each new episode is replaced by a uniform request
    reqs = planner.plan([make_episode(rng), make_episode(rng)])
    assert [r.reason["planner"] for r in reqs] == ["seed", "seed"]


def test_threshold_is_a_running_percentile_and_requests_say_why():
    rng = np.random.default_rng(2)
    cfg = acfg(percentile=75.0, budget_per_round=100, min_distance=0.0, redraw_agent=False)
    planner = ActivePlanner(cfg, step_scorer("m7"), rng)
    ep = make_episode(rng, steps=20)
    reqs = planner.plan([ep])
    assert planner.threshold == pytest.approx(np.percentile(np.arange(20), 75))
    steps = sorted(r.reason["step"] for r in reqs)
    assert steps == [s for s in range(20) if s > planner.threshold]
    top = reqs[0]
    assert top.reason == {"model_version": "m7", "score": 19.0, "source_episode": ep.meta.episode_id,
                          "step": 19, "planner": "active", "threshold": planner.threshold}
    assert top.priority > reqs[-1].priority  # higher score, higher priority
    # the request starts at the scored state, velocities included, no prefix
    assert top.start_state == state_at(ep, 19) and top.action_prefix == []
    assert top.start_state["object"][:2] == [ep.states[19, COL["obj_x"]], ep.states[19, COL["obj_y"]]]
    assert top.idempotency_key == f"active:{ep.meta.episode_id}:19"


def test_threshold_adapts_to_recent_scores_and_resets_on_a_new_champion():
    rng = np.random.default_rng(3)
    version = {"v": "m1", "scale": 1.0}
    scorer = lambda ep: Scores(version["v"], np.full(len(ep), version["scale"]))  # noqa: E731
    planner = ActivePlanner(acfg(budget_per_round=5, min_distance=0.0), scorer, rng)
    planner.plan([make_episode(rng)])
    assert planner.threshold == pytest.approx(1.0)
    version.update(v="m2", scale=0.01)  # a better champion: its disagreement is far lower
    planner.plan([make_episode(rng)])
    assert planner.threshold == pytest.approx(0.01)


def test_replay_prefix_mode_starts_at_the_episode_start():
    rng = np.random.default_rng(4)
    cfg = acfg(budget_per_round=1, replay_prefix=True)
    ep = make_episode(rng, steps=12)
    [req] = ActivePlanner(cfg, step_scorer(), rng).plan([ep])
    assert req.start_state == ep.meta.start_state
    assert req.action_prefix == ep.actions[:11].astype(float).tolist()


def test_candidates_are_diverse():
    rng = np.random.default_rng(5)
    # one episode that sits still (every step the same state) and one that moves a lot
    still = make_episode(rng, steps=30, jitter=0.0)
    moving = make_episode(rng, steps=30, jitter=400.0)
    cfg = acfg(percentile=0.0, budget_per_round=10, min_distance=0.15)
    reqs = ActivePlanner(cfg, step_scorer(), rng).plan([still, moving])
    from_still = [r for r in reqs if r.reason["source_episode"] == still.meta.episode_id]
    assert len(from_still) <= 1  # identical states are one request, however uncertain
    feats = [state_features(r.shape, r.start_state["agent"], r.start_state["object"], r.start_state["physics"])
             for r in reqs]
    assert min(np.linalg.norm(a - b) for i, a in enumerate(feats) for b in feats[i + 1:]) >= 0.15


def test_select_diverse_keeps_highest_scores_and_respects_earlier_requests():
    f = lambda *v: np.array(v, dtype=float)  # noqa: E731
    ep = make_episode(np.random.default_rng(6))
    cands = [Candidate(3.0, ep, 0, f(0, 0)), Candidate(2.0, ep, 1, f(0.01, 0)), Candidate(1.0, ep, 2, f(1, 0))]
    assert [c.step for c in select_diverse(cands, 5, 0.1)] == [0, 2]
    assert [c.step for c in select_diverse(cands, 1, 0.1)] == [0]
    assert [c.step for c in select_diverse(cands, 5, 0.1, taken=[f(0, 0.02)])] == [2]


def test_select_diverse_allows_a_pose_as_many_times_as_repeats_says():
    """``repeats`` N: a candidate is kept while fewer than N kept ones (earlier requests included) lie within
    min_distance of it; 1 is each pose once."""
    f = lambda *v: np.array(v, dtype=float)  # noqa: E731
    ep = make_episode(np.random.default_rng(6))
    cands = [Candidate(4.0 - i, ep, i, f(0.01 * i, 0)) for i in range(4)] + [Candidate(0.5, ep, 9, f(1, 0))]
    assert [c.step for c in select_diverse(cands, 9, 0.1, repeats=3)] == [0, 1, 2, 9]
    assert [c.step for c in select_diverse(cands, 9, 0.1, taken=[f(0, 0)], repeats=3)] == [0, 1, 9]
    assert [c.step for c in select_diverse(cands, 9, 0.1, repeats=1)] == [0, 9]
    with pytest.raises(ValueError, match="repeats"):
        acfg(repeats=0)


def test_bench_loop_takes_repeats(tmp_path):
    from orchestrator.cli import build_parser
    args = build_parser().parse_args(["bench", "loop", "--repeats", "3", "--out", str(tmp_path / "o")])
    assert args.repeats == 3


def test_budget_per_round_and_queue_depth_caps(tmp_path):
    rng = np.random.default_rng(8)
    queue = RequestQueue(tmp_path / "q.sqlite")
    cfg = acfg(percentile=0.0, budget_per_round=3, max_queue_depth=5, min_distance=0.0)
    planner = ActivePlanner(cfg, step_scorer(), rng, queue_depth=lambda: queue.counts().get("queued", 0))
    eps = [make_episode(rng, steps=30) for _ in range(4)]
    first = planner.plan(eps)
    assert len(first) == 3  # the round's budget, not 4 * 30 candidates
    for r in first:
        queue.enqueue(r)
    second = planner.plan(eps)  # the same episodes again: other steps, never the same ones
    assert len(second) == 2  # only room for 2 more under max_queue_depth=5
    assert {r.idempotency_key for r in first}.isdisjoint(r.idempotency_key for r in second)
    for r in second:
        queue.enqueue(r)
    assert planner.plan([make_episode(rng)]) == [] and queue.counts()["queued"] == 5
    uni = UniformPlanner(UniformPlannerConfig(max_queue_depth=5), rng,
                         queue_depth=lambda: queue.counts().get("queued", 0))
    assert uni.seed(10) == [] and uni.plan(eps) == []


def test_active_requests_round_trip_through_the_queue(tmp_path):
    rng = np.random.default_rng(9)
    queue = RequestQueue(tmp_path / "q.sqlite")
    planner = ActivePlanner(acfg(budget_per_round=2), step_scorer(), rng)
    ep = make_episode(rng)
    reqs = planner.plan([ep])
    created = [queue.enqueue(r)[1] for r in reqs]
    assert created == [True, True]
    # planning the same episode again (e.g. after a restart) asks for nothing new
    again = ActivePlanner(acfg(budget_per_round=2), step_scorer(), rng).plan([ep])
    assert [queue.enqueue(r)[1] for r in again] == [False, False]
    leased = queue.lease("w1", ["push"], [ep.meta.shape], 30.0)
    assert leased is not None and leased.request.reason["planner"] == "active"
    assert leased.request.reason["step"] == 19  # highest score leased first


def test_with_a_real_ensemble_as_the_scorer():
    rng = np.random.default_rng(10)
    ensemble = Ensemble(PredictorConfig(image_size=16, context=2, widths=(4, 4, 4), action_hidden=8),
                        members=3, seed=0)
    scorer = lambda ep: Scores("tiny", ensemble.disagreement(ep.frames, ep.actions))  # noqa: E731
    planner = ActivePlanner(acfg(budget_per_round=3, min_distance=0.0), scorer, rng)
    reqs = planner.plan([make_episode(rng, steps=12)])
    assert 1 <= len(reqs) <= 3
    assert all(r.reason["score"] > planner.threshold for r in reqs)
    assert all(0 < r.reason["step"] < 11 for r in reqs)  # step 0 has no context, step 11 no successor


def test_both_arms_share_the_policy_mix():
    mix = PolicyMix(push_weight=0.5)
    rng = np.random.default_rng(11)
    draws = [mix.draw(rng) for _ in range(200)]
    assert {name for name, _ in draws} == {"push", "random_waypoints"}
    assert {p["side"] for name, p in draws if name == "push"} == {"left", "right", "top", "bottom"}
    with pytest.raises(ValueError, match="push_weight"):
        PolicyMix(push_weight=1.5)


def test_bad_configs_say_what_was_expected():
    with pytest.raises(ValueError, match="percentile"):
        ActivePlannerConfig(percentile=100.0)
    for memory in (-1, 2.5, True):
        with pytest.raises(ValueError, match=f"memory must be a whole number of at least 0, found {memory!r}"):
            ActivePlannerConfig(memory=memory)
    with pytest.raises(ValueError, match="shapes"):
        UniformPlannerConfig(shapes=("hexagon",))
    assert isinstance(UniformPlanner(UniformPlannerConfig(), np.random.default_rng(0)).seed(1)[0], NewRequest)


def test_requests_stay_in_the_task_space_start_at_rest_away_from_the_object_and_spread_over_shapes():
    rng = np.random.default_rng(12)
    eps = []
    for shape in ("T", "L"):
        ep = make_episode(rng, steps=30, shape=shape, jitter=400.0)
        ep.states[:, COL["agent_vx"]] = 300.0  # moving fast everywhere
        eps.append(ep)
    cfg = ActivePlannerConfig(percentile=0.0, budget_per_round=8, min_distance=0.0, max_shape_share=0.5)
    def scorer(ep):
        return Scores("m1", np.arange(len(ep), dtype=float) * (10.0 if ep.meta.shape == "T" else 1.0))
    reqs = ActivePlanner(cfg, scorer, rng).plan(eps)
    lo, hi = protocol.OBJECT_RANGE
    alo, ahi = protocol.AGENT_RANGE
    assert reqs
    for r in reqs:
        s = r.start_state
        assert lo <= s["object"][0] <= hi and lo <= s["object"][1] <= hi
        assert alo <= s["agent"][0] <= ahi and alo <= s["agent"][1] <= ahi
        assert s["agent_vel"] == [0.0, 0.0] and s["object_vel"] == [0.0, 0.0, 0.0]
        # the object is the scored state's, the agent is drawn as a uniform start draws it
        src = next(e for e in eps if e.meta.episode_id == r.reason["source_episode"])
        step = r.reason["step"]
        assert s["object"][:2] == [src.states[step, COL["obj_x"]], src.states[step, COL["obj_y"]]]
        assert math.dist(s["agent"], s["object"][:2]) >= AGENT_CLEARANCE
    # T scores ten times higher, yet at most half the round is T
    assert sum(r.shape == "T" for r in reqs) <= 4


def with_policy(ep: Episode, policy: str) -> Episode:
    return dataclasses.replace(ep, meta=dataclasses.replace(ep.meta, policy=policy))


def test_choose_policy_favours_the_policy_whose_episodes_the_champion_disagrees_on_most():
    rng = np.random.default_rng(13)
    champion = {"version": "m1", "level": {"push": 1.0, "random_waypoints": 3.0}}
    # a real scorer: every step of an episode scores its policy's level (plus a ramp, so steps differ)
    def scorer(ep: Episode) -> Scores:
        return Scores(champion["version"], champion["level"][ep.meta.policy] * (1 + np.arange(len(ep)) / 100))
    cfg = acfg(choose_policy=True, policy_sharpness=4.0, policy_floor=0.1, percentile=0.0,
               budget_per_round=300, max_queue_depth=1000, min_distance=0.0)
    planner = ActivePlanner(cfg, scorer, rng)
    assert planner.policy_weights() == {"push": 0.5, "random_waypoints": 0.5}  # nothing scored: the mix
    # only push episodes scored so far: the untried policy counts as the best, so both are equally likely
    planner.plan([with_policy(make_episode(rng, steps=30), "push")])
    assert planner.policy_weights() == pytest.approx({"push": 0.5, "random_waypoints": 0.5})
    eps = [with_policy(make_episode(rng, steps=40), p) for p in MIX_POLICIES * 4]
    reqs = planner.plan(eps)
    mean = {"push": 1.0 * 1.195, "random_waypoints": 3.0 * 1.195}  # the ramp's mean over 40 steps is 1.195
    raw = {p: (m / mean["random_waypoints"]) ** 4 for p, m in mean.items()}
    expected = {p: 0.1 + 0.8 * r / sum(raw.values()) for p, r in raw.items()}
    assert planner.policy_weights() == pytest.approx(expected, abs=2e-3)  # ~0.11 push, ~0.89 waypoints
    assert len(reqs) > 200
    share = sum(r.policy == "random_waypoints" for r in reqs) / len(reqs)
    assert 0.8 < share < 0.97
    assert all(r.reason["policy_weights"] == pytest.approx(expected, abs=2e-3) for r in reqs)
    assert all(r.policy_params == {} for r in reqs if r.policy == "random_waypoints")
    assert all(set(r.policy_params) == {"side", "noise"} for r in reqs if r.policy == "push")
    # a new champion that disagrees most on pushes: the old scores are dropped and the choice flips
    champion.update(version="m2", level={"push": 0.02, "random_waypoints": 0.01})
    planner.plan([with_policy(make_episode(rng, steps=40), p) for p in MIX_POLICIES])
    weights = planner.policy_weights()
    assert weights["push"] == pytest.approx(0.1 + 0.8 * 1 / (1 + 0.5 ** 4)) and weights["push"] > 0.8


def test_choose_policy_is_off_by_default_and_its_settings_are_checked():
    assert not ActivePlannerConfig().choose_policy
    with pytest.raises(ValueError, match="policy_floor"):
        ActivePlannerConfig(choose_policy=True, policy_floor=0.6)
    with pytest.raises(ValueError, match="policy_sharpness"):
        ActivePlannerConfig(policy_sharpness=-1.0)


def test_within_policy_ranks_steps_against_their_own_policy():
    rng = np.random.default_rng(21)
    level = {"push": 1.0, "random_waypoints": 5.0}
    # a real scorer: the policy's level (waypoints move more, so every member errs more) times the
    # episode's own surprise, times a small ramp so steps differ
    surprise: dict[str, float] = {}
    def scorer(ep: Episode) -> Scores:
        return Scores("m1", level[ep.meta.policy] * surprise[ep.meta.episode_id] * (1 + np.arange(len(ep)) / 100))
    eps = []
    for i, policy in enumerate(MIX_POLICIES * 4):
        ep = with_policy(make_episode(rng, steps=20), policy)
        # one push episode is 3x as surprising as the other pushes; the waypoint episodes differ little
        surprise[ep.meta.episode_id] = (3.0 if i == 6 else 1.0) if policy == "push" else 1.0 + 0.02 * i
        eps.append(ep)
    cfg = dict(percentile=50.0, budget_per_round=4, max_queue_depth=100, min_distance=0.0)

    def sources(planner: ActivePlanner) -> list[str]:
        by_id = {ep.meta.episode_id: ep for ep in eps}
        return [by_id[r.reason["source_episode"]].meta.policy for r in planner.plan(eps)]

    assert sources(ActivePlanner(acfg(**cfg), scorer, np.random.default_rng(0))) == ["random_waypoints"] * 4
    within = sources(ActivePlanner(acfg(**cfg, within_policy=True), scorer, np.random.default_rng(0)))
    assert within == ["push"] * 4
    assert not ActivePlannerConfig().within_policy

    # one episode at a time, as the service plans each upload: the surprising push is measured against
    # the pushes before it, not against itself
    planner = ActivePlanner(acfg(**cfg, within_policy=True), scorer, np.random.default_rng(0))
    best = {}
    for ep in eps:
        reqs = planner.plan([ep])
        best[ep.meta.episode_id] = max((r.reason["score"] for r in reqs), default=0.0)
        assert all(r.reason["within_policy"] for r in reqs)
    assert planner.policy_means() == pytest.approx({"push": 1.5 * 1.095, "random_waypoints": 5.0 * 1.08 * 1.095})
    surprising = eps[6].meta.episode_id
    assert best[surprising] > 1.5 * max(v for k, v in best.items() if k != surprising)

    # the function itself: scores over their policy's mean; a policy without a positive mean is left alone
    scores = [(with_policy(eps[0], "push"), Scores("m1", np.array([np.nan, 2.0, 4.0]))),
              (with_policy(eps[2], "random_waypoints"), Scores("m1", np.array([1.0, np.nan]))),
              (with_policy(eps[4], "scripted"), Scores("m1", np.array([3.0])))]
    out = relative_to_policy(scores, {"push": 4.0, "random_waypoints": 0.0})
    assert np.allclose(out[0][1].per_step, [np.nan, 0.5, 1.0], equal_nan=True)
    assert out[1][1] is scores[1][1] and out[2][1] is scores[2][1]


def test_a_round_left_short_is_filled_to_its_end_not_by_a_whole_round():
    """A dead request leaves round 2 at 47 of 48: one more request, so the retrain lands on 48 again."""
    collected = [47]
    rounds = RoundPlanner(UniformPlanner(UniformPlannerConfig(max_queue_depth=1000), np.random.default_rng(0)),
                          round_episodes=24, budget=96, collected=lambda: collected[0], outstanding=lambda: 0)
    assert len(rounds.release(24 - collected[0] % 24)) == 1
    collected[0] = 48
    assert len(rounds.release()) == 24  # a whole round after the retrain
    collected[0] = 90
    assert len(rounds.release()) == 6   # never past the budget


def test_a_promotion_while_a_batch_is_scored_leaves_scores_of_one_champion():
    rng = np.random.default_rng(0)
    calls = []

    def scorer(ep):  # the champion changes from m1 (scores ~1) to m2 (~1e-3) after the batch's first episode
        calls.append(1)
        if len(calls) <= 1:
            return Scores("m1", rng.uniform(0.5, 1.5, len(ep)))
        return Scores("m2", rng.uniform(0, 1e-3, len(ep)))

    planner = ActivePlanner(acfg(budget_per_round=4, min_distance=0.0, explore_fraction=0.0), scorer, rng)
    requests = planner.plan([make_episode(rng) for _ in range(3)])
    assert len(calls) == 4  # the first episode was scored again by m2
    assert {r.reason["model_version"] for r in requests} == {"m2"} and planner.threshold < 1e-3
    assert len(planner.plan([make_episode(rng) for _ in range(2)])) == 4  # m2's uncertain states get requests


def test_a_round_cut_short_by_the_budget_remembers_only_the_requests_it_queued():
    """The last round has room for 2 of the active planner's 6: it plans 2, and only their states are kept away
    from by the next plan. (The old round cut the plan after the planner had remembered all 6.)"""
    rng = np.random.default_rng(0)
    planner = ActivePlanner(acfg(budget_per_round=6, explore_fraction=0.0, min_distance=0.0), step_scorer(),
                            np.random.default_rng(1))
    rounds = RoundPlanner(planner, round_episodes=6, budget=8, collected=lambda: 6, outstanding=lambda: 0)
    rounds.plan([make_episode(rng) for _ in range(4)])
    released = rounds.release()
    assert len(released) == 2 and all(r.reason.get("score") is not None for r in released)
    assert len(planner._requested_steps) == 2
    assert len(UniformPlanner(UniformPlannerConfig(max_queue_depth=1000), rng).plan([make_episode(rng)] * 5,
                                                                                    limit=3)) == 3
