"""The active planner's per-shape floor (``ActivePlannerConfig.min_per_shape``): a round its picks leave short
gets uniform starts until every shape has that many requests, the shape with the fewest first."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator import protocol
from orchestrator.loopconfig import LoopBenchConfig
from orchestrator.planner import ActivePlanner, ActivePlannerConfig
from orchestrator.uniform import UniformPlannerConfig
from tests.orchestrator.test_planner import acfg, make_episode, step_scorer


def round_of(cfg: ActivePlannerConfig, shapes: tuple[str, ...], queued: int = 0) -> list:
    """One planned round over one episode per entry of ``shapes`` (every step a candidate, no distance)."""
    rng = np.random.default_rng(0)
    episodes = [make_episode(rng, steps=30, shape=shape) for shape in shapes]
    planner = ActivePlanner(cfg, step_scorer(), np.random.default_rng(1), queue_depth=lambda: queued)
    return planner.plan(episodes)


def floor_cfg(**kw) -> ActivePlannerConfig:
    return acfg(percentile=0.0, min_distance=0.0, **kw)


def test_a_short_round_gets_every_shape_to_the_floor_fewest_first_and_its_picks_count():
    # a cap of 1 per shape: the picks are one T and one box, six short of the budget
    reqs = round_of(floor_cfg(budget_per_round=8, max_shape_share=0.125, min_per_shape=2), ("T", "box"))
    assert [r.reason["planner"] for r in reqs[:2]] == ["active", "active"]
    assert sorted(r.shape for r in reqs[:2]) == ["T", "box"]
    floor = reqs[2:]
    assert all(r.reason["planner"] == "shape-floor" for r in floor)
    assert [r.shape for r in floor] == ["L", "disk", "T", "box", "L", "disk"]  # fewest first, ties in SHAPES order
    assert {s: sum(r.shape == s for r in reqs) for s in protocol.SHAPES} == dict.fromkeys(protocol.SHAPES, 2)
    for r in floor:  # uniform starts of their shape
        assert r.start_state["shape"] == r.shape and r.action_prefix == [] and r.priority == 0.0


def test_the_floor_never_fills_past_the_budget_or_the_room():
    reqs = round_of(floor_cfg(budget_per_round=6, max_shape_share=0.25, min_per_shape=2), ("T", "box"))
    assert len(reqs) == 6  # two picks of each, then the rarest two shapes once: the round is full
    assert [r.shape for r in reqs if r.reason["planner"] == "shape-floor"] == ["L", "disk"]
    # room for 5 under the queue's depth (a budget of 8, a cap of 2 per shape)
    cfg = floor_cfg(budget_per_round=8, max_queue_depth=16, max_shape_share=0.25, min_per_shape=3)
    reqs = round_of(cfg, ("T",), queued=11)
    assert len(reqs) == 5 and sum(r.reason["planner"] == "active" for r in reqs) == 2
    assert [r.shape for r in reqs[2:]] == ["box", "L", "disk"]


def test_no_floor_when_the_picks_fill_the_round_or_it_is_off():
    reqs = round_of(floor_cfg(budget_per_round=4, min_per_shape=2), ("T",))
    assert [r.reason["planner"] for r in reqs] == ["active"] * 4 and {r.shape for r in reqs} == {"T"}
    reqs = round_of(floor_cfg(budget_per_round=8, max_shape_share=0.25), ("T", "box"))
    assert [r.reason["planner"] for r in reqs] == ["active"] * 4  # the rest is the caller's top-up
    # explore requests count as picks do: four disks (the uniform draw's only shape), a pick of T, box and L each
    explore = dict(budget_per_round=8, max_shape_share=0.25, explore_fraction=0.5,
                   seed_uniform=UniformPlannerConfig(shape_weights=(0.0, 0.0, 0.0, 1.0)))
    reqs = round_of(floor_cfg(min_per_shape=1, **explore), ("T", "box", "L"))
    assert sorted(r.reason["planner"] for r in reqs) == ["active"] * 3 + ["explore"] * 4
    reqs = round_of(floor_cfg(min_per_shape=2, **explore), ("T", "box", "L"))
    assert [(r.reason["planner"], r.shape) for r in reqs[7:]] == [("shape-floor", "T")]


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2"])
def test_min_per_shape_must_be_a_whole_number_of_at_least_0(bad):
    with pytest.raises(ValueError, match=f"min_per_shape must be a whole number of at least 0, found {bad!r}"):
        ActivePlannerConfig(min_per_shape=bad)
    assert ActivePlannerConfig(min_per_shape=0).min_per_shape == 0


def test_min_per_shape_is_refused_with_shapes_by_progress():
    with pytest.raises(ValueError, match="min_per_shape and shapes_by_progress exclude each other"):
        ActivePlannerConfig(min_per_shape=2, shapes_by_progress=True)
    with pytest.raises(ValueError, match="min_per_shape and shapes_by_progress exclude each other"):
        LoopBenchConfig(shapes_by_progress=True, active=ActivePlannerConfig(min_per_shape=2))
    assert not LoopBenchConfig(shapes_by_progress=True).active.min_per_shape
