"""Every request the active planner makes passes the service's own checks (``RequestSpec``, which a worker's
grant is checked by too), whatever the stored episode it comes from holds.

Real episodes from the simulator, stored in and read back from a real catalog (SQLite and MCAP), and a real
request queue. Two ways a request used to fail the checks: a priority past MAX_PRIORITY (the priority is the
score over the threshold, and the threshold of an ensemble whose clamped predictions agree exactly on most steps
is near 0; a float64 scorer's ratio could even overflow, and the whole batch failed), and a state no worker can
start from (an ingested episode's angle out of bounds), which workers refused lease after lease until the
request was dead.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from orchestrator import protocol
from orchestrator.messages import RequestSpec
from orchestrator.planner import ActivePlanner, ActivePlannerConfig, Scores
from storage.catalog import Catalog
from storage.queue import RequestQueue
from storage.records import STATE_FIELDS, Episode
from tests.orchestrator.test_planner_redraw import approach

COL = {n: i for i, n in enumerate(STATE_FIELDS)}


def stored(catalog: Catalog, ep: Episode) -> Episode:
    """``ep`` as the catalog gives it back, once stored."""
    catalog.add_episode(ep)
    return catalog.load(ep.meta.episode_id)


def renamed(ep: Episode, episode_id: str) -> Episode:
    """``ep`` under another id."""
    return dataclasses.replace(ep, meta=dataclasses.replace(ep.meta, episode_id=episode_id))


def valid(request) -> RequestSpec:
    """The request as the service checks one (raises ProtocolError)."""
    return RequestSpec(**dataclasses.asdict(request))


def cfg(**kw) -> ActivePlannerConfig:
    return ActivePlannerConfig(**{"budget_per_round": 4, "max_shape_share": 1.0, **kw})


def test_a_threshold_near_zero_gives_priorities_within_the_services_bounds(tmp_path):
    catalog = Catalog(tmp_path / "data")
    ep = stored(catalog, approach([60.0, 60.0]))

    def clamped(ep: Episode) -> Scores:
        """Most steps as an ensemble scores them whose clamped predictions agree (all but exactly), a few not."""
        per_step = np.full(len(ep), 1e-16)
        per_step[25:29] = [3e-2, 2e-2, 1e-2, 5e-3]
        return Scores("m1", per_step)

    planner = ActivePlanner(cfg(min_distance=0.0), clamped, np.random.default_rng(0))
    reqs = planner.plan([ep])
    assert 0 < planner.threshold < 1e-15 and len(reqs) >= 2
    for r in reqs:
        assert r.priority == protocol.MAX_PRIORITY  # 1e14 and more, bounded
        assert valid(r).priority == protocol.MAX_PRIORITY
    queue = RequestQueue(catalog.db_path)
    assert [created for _, created in queue.enqueue_many(reqs)] == [True] * len(reqs)

    # a float64 scorer's ratio can overflow: it was an infinite priority, and the whole batch failed
    overflow = lambda ep: Scores("m2", np.where(clamped(ep).per_step > 1e-3, 1e300, 1e-300))  # noqa: E731
    reqs = ActivePlanner(cfg(min_distance=0.0), overflow, np.random.default_rng(0)).plan([ep])
    assert reqs and all(valid(r).priority == protocol.MAX_PRIORITY for r in reqs)


def test_a_state_no_worker_can_start_from_is_not_requested_and_is_said_once(tmp_path, caplog):
    catalog = Catalog(tmp_path / "data")
    good = stored(catalog, approach([60.0, 60.0]))
    spun = []
    for i, seed in enumerate((6, 7)):  # episodes collected elsewhere whose angles count turns in the millions
        ep = renamed(approach([60.0, 440.0], seed=seed), f"spun-{i}")
        ep.states[:, COL["obj_theta"]] += 2e6
        spun.append(stored(catalog, ep))
    assert spun[0].states[0, COL["obj_theta"]] > 1e6  # finite: the catalog holds it
    scorer = lambda ep: Scores("m1", np.arange(len(ep), dtype=float))  # noqa: E731
    planner = ActivePlanner(cfg(percentile=0.0, budget_per_round=8), scorer, np.random.default_rng(0))
    with caplog.at_level(logging.DEBUG, logger="orchestrator.planner"):
        assert planner.plan([spun[0]]) == []
        reqs = planner.plan([good])
        assert planner.plan([spun[1]]) == []
    assert reqs and all(valid(r) for r in reqs)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "start_state.object[2]" in warnings[0].getMessage()
    assert "spun-0" in warnings[0].getMessage()
    assert any("spun-1" in r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG)


@pytest.mark.parametrize("kw", [{}, {"redraw_agent": False, "at_rest": False}, {"replay_prefix": True}])
def test_requests_from_real_episodes_pass_the_services_checks(tmp_path, kw):
    """The usual case, in the settings that keep more of the episode's state: nothing is dropped."""
    catalog = Catalog(tmp_path / "data")
    eps = [stored(catalog, approach(agent, seed=s)) for s, agent in enumerate(([60.0, 60.0], [450.0, 80.0]))]
    def speed(ep):
        return Scores("m1", np.hypot(ep.states[:, COL["agent_vx"]], ep.states[:, COL["agent_vy"]]))
    reqs = ActivePlanner(cfg(percentile=0.0, budget_per_round=12, min_distance=0.0, **kw), speed,
                         np.random.default_rng(0)).plan(eps)
    assert len(reqs) == 12 and all(valid(r) for r in reqs)


def test_scores_that_mark_no_state_ask_for_nothing_and_keep_the_threshold(tmp_path):
    """Checked, nothing wrong: an episode shorter than the model's context (a real tiny ensemble scores no step),
    scores all NaN (another frame size), all infinite, or all equal give no request, and leave the threshold
    of the episodes before them as it was; an episode beside them in the batch is planned as usual."""
    from uncertainty.ensemble import Ensemble
    from uncertainty.model import PredictorConfig
    catalog = Catalog(tmp_path / "data")
    full = approach([60.0, 60.0])
    short = stored(catalog, renamed(dataclasses.replace(full, frames=full.frames[:2], actions=full.actions[:2],
                                                        states=full.states[:2]), "short"))
    ensemble = Ensemble(PredictorConfig(image_size=16, context=2, widths=(4, 4, 4), action_hidden=8), members=3,
                        seed=0)
    assert np.isnan(ensemble.disagreement(short.frames, short.actions)).all()
    special = {"short": None, "nan": np.nan, "inf": np.inf, "equal": 0.5}
    eps = {name: renamed(approach([60.0, 60.0], seed=9), name) for name in ("nan", "inf", "equal")}
    eps["short"] = short

    def scorer(ep: Episode) -> Scores:
        value = special.get(ep.meta.episode_id, "real")
        if value is None or value == "real":
            return Scores("tiny", ensemble.disagreement(ep.frames, ep.actions))
        return Scores("tiny", np.full(len(ep), value))

    planner = ActivePlanner(cfg(), scorer, np.random.default_rng(0))
    first = planner.plan([stored(catalog, approach([60.0, 60.0], seed=8))])
    assert first and np.isfinite(planner.threshold)
    threshold = planner.threshold
    for name in ("short", "nan", "inf"):
        assert planner.plan([eps[name]]) == [] and planner.threshold == threshold
    fresh = ActivePlanner(cfg(), scorer, np.random.default_rng(0))
    assert fresh.plan([eps["equal"]]) == [] and fresh.threshold == 0.5  # nothing above it: the top-up's turn
    mixed = ActivePlanner(cfg(), scorer, np.random.default_rng(0)).plan([short, approach([60.0, 60.0], seed=8)])
    assert mixed and "short" not in {r.reason["source_episode"] for r in mixed}
