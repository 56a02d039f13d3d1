"""The active planner with a redrawn agent (the default): only what a request keeps counts.

A request keeps the scored state's object and draws the agent anew, so neither its diversity distance
nor its task-space check may count the source state's agent. The steps before the pusher reaches the
object all hold the object's start pose; counting the agent made them pass as different states.
"""

from __future__ import annotations

import numpy as np

from orchestrator import protocol
from orchestrator.diversity import state_features
from orchestrator.planner import ActivePlanner, ActivePlannerConfig, Scores, state_at
from storage.records import STATE_FIELDS, Episode
from workers.collect import collect_episode

COL = {n: i for i, n in enumerate(STATE_FIELDS)}
OBJECT = [330.0, 330.0, 0.0]


def approach(agent: list[float], seed: int = 3) -> Episode:
    """A real push episode: the pusher crosses the table to the object (at rest, in its start pose, for
    the first dozen steps), then pushes it."""
    return collect_episode(start_state={"shape": "T", "agent": agent, "object": OBJECT}, policy="push",
                           policy_params={"side": "right", "noise": 0.0}, seed=seed, steps=40, image_size=16)


def pusher_speed(ep: Episode) -> Scores:
    """A scorer that follows the pusher's speed, as the champion's disagreement does (BENCHMARKS.md)."""
    return Scores("m1", np.hypot(ep.states[:, COL["agent_vx"]], ep.states[:, COL["agent_vy"]]))


def kept(reqs) -> list[np.ndarray]:
    """The requests' states as they start, less the redrawn agent (at one place for all)."""
    return [state_features(r.shape, (0.0, 0.0), r.start_state["object"], r.start_state["physics"]) for r in reqs]


def test_one_object_pose_is_one_request_however_far_the_pusher_moved():
    ep = approach([60.0, 60.0])
    at_rest = np.all(ep.states[:, [COL["obj_x"], COL["obj_y"], COL["obj_theta"]]] == OBJECT, axis=1)
    assert at_rest[:12].all()  # the pusher travels hundreds of units meanwhile
    cfg = ActivePlannerConfig(percentile=0.0, budget_per_round=8, max_queue_depth=8, max_shape_share=1.0)
    reqs = ActivePlanner(cfg, pusher_speed, np.random.default_rng(0)).plan([ep])
    assert len(reqs) >= 2
    feats = kept(reqs)
    gaps = [np.linalg.norm(a - b) for i, a in enumerate(feats) for b in feats[i + 1:]]
    assert min(gaps) >= cfg.min_distance
    assert sum(r.start_state["object"] == OBJECT for r in reqs) == 1


def test_a_pose_requested_before_is_not_requested_again_from_the_episode_it_gave():
    cfg = ActivePlannerConfig(percentile=0.0, budget_per_round=8, max_queue_depth=8, max_shape_share=1.0)
    planner = ActivePlanner(cfg, pusher_speed, np.random.default_rng(0))
    first = planner.plan([approach([60.0, 60.0])])
    resting = next(r for r in first if r.start_state["object"] == OBJECT)
    # The episode that request gives starts in the same object pose with another pusher.
    again = approach(resting.start_state["agent"], seed=5)
    second = planner.plan([again])
    assert all(r.start_state["object"] != OBJECT for r in second)
    earlier = kept(first)
    assert all(min(np.linalg.norm(f - e) for e in earlier) >= cfg.min_distance for f in kept(second))


def test_a_redrawn_agent_is_not_held_to_the_task_space_but_a_kept_one_is():
    ep = approach([60.0, 60.0])
    ep.states[:, COL["agent_x"]] = protocol.AGENT_RANGE[0] - 10.0  # the pusher by the wall, the object inside
    cfg = dict(percentile=0.0, budget_per_round=4, max_queue_depth=4, max_shape_share=1.0)
    redrawn = ActivePlanner(ActivePlannerConfig(**cfg), pusher_speed, np.random.default_rng(0)).plan([ep])
    assert redrawn
    alo, ahi = protocol.AGENT_RANGE
    assert all(alo <= r.start_state["agent"][0] <= ahi for r in redrawn)
    kept_agent = ActivePlannerConfig(**cfg, redraw_agent=False)
    assert ActivePlanner(kept_agent, pusher_speed, np.random.default_rng(0)).plan([ep]) == []


def test_without_at_rest_the_object_keeps_its_velocity_and_a_redrawn_pusher_starts_still():
    """``at_rest=False``: the state's velocities are kept, but not the old pusher's for a pusher drawn elsewhere
    (one far from the object flying at the speed the old one had next to it means nothing)."""
    ep = approach([60.0, 60.0])
    cfg = dict(percentile=0.0, budget_per_round=4, max_queue_depth=4, max_shape_share=1.0, at_rest=False)
    reqs = ActivePlanner(ActivePlannerConfig(**cfg), pusher_speed, np.random.default_rng(0)).plan([ep])
    source = [state_at(ep, r.reason["step"]) for r in reqs]
    assert any(max(map(abs, s["agent_vel"])) > 100 for s in source)  # pushers that were moving fast
    assert any(max(map(abs, s["object_vel"])) > 50 for s in source)  # and an object that was moving
    assert all(r.start_state["agent_vel"] == [0.0, 0.0] for r in reqs)
    assert [r.start_state["object_vel"] for r in reqs] == [s["object_vel"] for s in source]
    # a kept pusher keeps its velocity (it is the state's own pusher, where it was)
    kept_agent = ActivePlanner(ActivePlannerConfig(**cfg, redraw_agent=False), pusher_speed,
                               np.random.default_rng(0)).plan([ep])
    assert kept_agent and all(r.start_state == state_at(ep, r.reason["step"]) for r in kept_agent)
