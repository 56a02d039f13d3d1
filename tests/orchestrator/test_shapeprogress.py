"""Splitting a round over shapes by what data of each has bought (orchestrator.shapeprogress), and the active
planner that does so (``ActivePlannerConfig.shapes_by_progress``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orchestrator.planner import ActivePlanner, Scores
from orchestrator.shapeprogress import ShapeProgress
from tests.orchestrator.test_planner import acfg, make_episode

SHAPES = ("T", "box", "L", "disk")


def _scores(ep, error: float, trained: bool | None, version: str = "m1") -> Scores:
    per_step = np.full(len(ep), error)
    per_step[0] = np.nan  # a step without context has no score (and no error)
    return Scores(version, np.arange(len(ep), dtype=float), per_step, trained)


def test_a_shapes_drop_is_how_much_its_error_fell_once_trained_on():
    rng, progress = np.random.default_rng(0), ShapeProgress(memory=2)
    t1, t2, t3, l1 = (make_episode(rng, shape=s) for s in ("T", "T", "T", "L"))
    progress.record(t1, _scores(t1, 5.0, False, "m1"))
    progress.record(t1, _scores(t1, 4.0, False, "m2"))  # the latest fresh error wins
    progress.record(l1, _scores(l1, 9.0, False, "m2"))
    assert {ep.meta.episode_id for ep in progress.waiting("m3")} == {t1.meta.episode_id, l1.meta.episode_id}
    assert progress.waiting("m2") == []  # already scored by m2
    progress.record(t1, _scores(t1, 1.0, True, "m3"))
    progress.record(t1, _scores(t1, 0.5, True, "m4"))  # only the first champion trained on it counts
    progress.record(l1, _scores(l1, 8.5, True, "m3"))
    progress.record(t2, _scores(t2, 2.0, True, "m3"))  # trained on, never seen fresh: nothing to compare
    progress.record(t3, Scores("m3", np.ones(len(t3))))  # a scorer that gives no errors: ignored
    assert progress.drops(SHAPES) == pytest.approx({"T": 0.75, "box": math.nan, "L": 0.5 / 9, "disk": math.nan},
                                              nan_ok=True)
    assert progress.counts(SHAPES) == {"T": 1, "box": 0, "L": 1, "disk": 0} and progress.waiting("m5") == []
    for i in range(3):  # the mean over the last `memory` episodes of a shape
        ep = make_episode(rng, shape="T")
        progress.record(ep, _scores(ep, 10.0 + i, False))
        progress.record(ep, _scores(ep, 10.0, True, "m9"))
    assert progress.drops(("T",))["T"] == pytest.approx((1 / 11 + 2 / 12) / 2) and progress.counts(("T",)) == {"T": 2}


def test_quotas_follow_the_drops_beyond_the_smallest_with_a_floor_and_try_unknown_shapes():
    rng, progress = np.random.default_rng(1), ShapeProgress()
    assert progress.quotas(16, SHAPES, 0.25) == {s: 4 for s in SHAPES}  # nothing known: equal
    for shape, fresh in (("T", 1.0), ("L", 2.0), ("box", 3.0)):
        ep = make_episode(rng, shape=shape)
        progress.record(ep, _scores(ep, fresh, False))
        if shape == "T":
            assert progress.quotas(16, SHAPES, 0.25) == {s: 4 for s in SHAPES}  # one known: nothing to compare
        progress.record(ep, _scores(ep, 1.0, True, "m2"))  # drops T 0, L 1/2, box 2/3; disk unknown
    quotas = progress.quotas(16, SHAPES, 0.25)
    # T (the smallest drop) gets only the floor; disk (unknown) counts as box (the largest); 16 * 0.335 = 5.36
    # for each of them, and the last request goes to one of the two, as the turn moves on: each twice in 4 calls
    calls = [quotas] + [progress.quotas(16, SHAPES, 0.25) for _ in range(3)]
    assert all(q["T"] == 1 and q["L"] == 4 and {q["box"], q["disk"]} == {5, 6} for q in calls)
    assert sum(q["box"] == 6 for q in calls) == sum(q["disk"] == 6 for q in calls) == 2
    turns = [progress.quotas(2, SHAPES, 1.0) for _ in range(4)]  # equal shares, 2 requests: every shape in turn
    assert all(sum(q.values()) == 2 for q in turns) and sum(q[s] for q in turns for s in SHAPES) == 8
    assert all(sum(q[s] for q in turns) == 2 for s in SHAPES)
    assert progress.quotas(16, SHAPES, 1.0) == {s: 4 for s in SHAPES}
    assert sum(progress.quotas(3, SHAPES, 0.0).values()) == 3
    assert progress.quotas(0, SHAPES, 0.25) == {s: 0 for s in SHAPES}
    for bad in ((-1, SHAPES, 0.25), (4, (), 0.25), (4, SHAPES, 1.5)):
        with pytest.raises(ValueError, match="need shapes"):
            progress.quotas(*bad)
    with pytest.raises(ValueError, match="memory must be >= 1"):
        ShapeProgress(0)


def test_the_active_planner_gives_the_shape_that_data_helps_more_and_fills_absent_shapes_uniformly():
    """T's error falls once trained on (a rare shape), L's does not (a capacity limit) although the ensemble
    disagrees more on it; box and disk are not in the new episodes: uniform starts of their own shape."""
    rng = np.random.default_rng(2)
    champion = {"version": "m1", "trained": set()}
    fresh_error = {"T": 4.0, "L": 6.0}
    seen_error = {"T": 1.0, "L": 5.9}

    def scorer(ep):
        trained = ep.meta.episode_id in champion["trained"]
        error = (seen_error if trained else fresh_error)[ep.meta.shape]
        disagreement = np.arange(len(ep), dtype=float) * (1.5 if ep.meta.shape == "L" else 1.0)
        return Scores(champion["version"], disagreement, np.full(len(ep), error), trained)

    planner = ActivePlanner(acfg(shapes_by_progress=True, budget_per_round=16, max_queue_depth=64, min_distance=0.0,
                                 progress_floor=0.25), scorer, rng)
    episodes = [make_episode(rng, shape=s) for s in ("T", "L") * 4]
    planner.observe(episodes)  # scored fresh, before the retrain
    champion["version"], champion["trained"] = "m2", {ep.meta.episode_id for ep in episodes}
    requests = planner.plan(episodes)
    assert planner.progress.drops(SHAPES) == pytest.approx({"T": 0.75, "box": math.nan, "L": 0.1 / 6, "disk": math.nan},
                                                      nan_ok=True)
    quotas = planner.shape_quotas
    assert sum(quotas.values()) == len(requests) == 16 and quotas == {"T": 5, "box": 5, "L": 1, "disk": 5}
    by_shape = {s: [r for r in requests if r.shape == s] for s in SHAPES}
    assert {s: len(v) for s, v in by_shape.items()} == quotas
    assert all(r.reason["planner"] == "active" and r.reason["shape_quotas"] == quotas
               for s in ("T", "L") for r in by_shape[s])
    assert all(r.reason["planner"] == "shape-fill" and r.start_state["shape"] == s
               for s in ("box", "disk") for r in by_shape[s])


def test_the_planner_scores_again_what_a_new_champion_trained_on():
    """Episodes seen fresh in one round get their trained error when a later champion has trained on them,
    even when they are not among the new episodes (the service plans as episodes arrive)."""
    rng = np.random.default_rng(3)
    champion = {"version": "m1", "trained": set()}

    def scorer(ep):
        trained = ep.meta.episode_id in champion["trained"]
        return Scores(champion["version"], np.ones(len(ep)), np.full(len(ep), 1.0 if trained else 3.0), trained)

    planner = ActivePlanner(acfg(shapes_by_progress=True, budget_per_round=4, max_queue_depth=64), scorer, rng)
    first = [make_episode(rng, shape="disk") for _ in range(2)]
    planner.plan(first)  # fresh under m1
    assert planner.progress.counts(SHAPES)["disk"] == 0
    champion["version"], champion["trained"] = "m2", {ep.meta.episode_id for ep in first}
    planner.plan([make_episode(rng, shape="T")])  # the disks are scored again by m2
    assert planner.progress.drops(("disk",))["disk"] == pytest.approx(2 / 3)
    assert planner.progress.counts(SHAPES)["disk"] == 2


def test_a_champion_that_cannot_say_what_it_trained_on_is_not_asked_again_and_again():
    """Scores with ``trained=None`` (a champion registered before models kept their episodes) record nothing:
    the waiting episodes are not scored again on every round."""
    rng = np.random.default_rng(4)
    champion, calls = {"version": "m1", "knows": True}, []

    def scorer(ep):
        calls.append(ep.meta.episode_id)
        return Scores(champion["version"], np.ones(len(ep)), np.full(len(ep), 2.0),
                      False if champion["knows"] else None)

    planner = ActivePlanner(acfg(shapes_by_progress=True, budget_per_round=4, max_queue_depth=64), scorer, rng)
    planner.plan([make_episode(rng, shape="disk") for _ in range(3)])  # fresh under m1
    champion["version"], champion["knows"] = "m2", False
    for _ in range(3):
        calls.clear()
        planner.plan([make_episode(rng, shape="T")])
        assert len(calls) == 1  # the new episode only


def test_an_episode_counts_once_and_the_config_is_checked():
    rng, progress = np.random.default_rng(5), ShapeProgress()
    ep = make_episode(rng, shape="box")
    progress.record(ep, _scores(ep, 2.0, False, "m1"))
    progress.record(ep, _scores(ep, 1.0, True, "m2"))
    progress.record(ep, _scores(ep, 3.0, False, "m1"))  # a rollback to a champion that had not seen it
    progress.record(ep, _scores(ep, 1.0, True, "m2"))
    assert progress.counts(("box",)) == {"box": 1} and progress.waiting("m3") == []
    for bad in ({"progress_floor": 1.5}, {"progress_memory": 0}, {"progress_horizon": 0}):
        with pytest.raises(ValueError, match="progress_floor in \\[0, 1\\], progress_memory >= 1"):
            acfg(**bad)
