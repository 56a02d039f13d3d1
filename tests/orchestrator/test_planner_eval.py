"""The active planner never builds a request from an eval episode's state.

Replaying an eval episode's action prefix under a new seed re-enacts its first steps exactly (the simulator is
deterministic), and the catalog's replay check, which keys on the seed, does not catch it: an eval leak. The
callers plan on train episodes only (uploads are stored as train, ``run`` resumes from the train split), so
the planner holds the line itself: it asks the catalog which split an episode is in.
"""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.planner import ActivePlanner, ActivePlannerConfig, Scores, in_eval_split
from storage.catalog import Catalog
from storage.records import Episode
from tests.orchestrator.test_planner_redraw import approach, pusher_speed


@pytest.fixture
def catalog_with_both(tmp_path) -> tuple[Catalog, Episode, Episode]:
    """A real catalog holding a train episode and an eval one (real push episodes)."""
    catalog = Catalog(tmp_path / "data")
    train, held_out = approach([60.0, 60.0], seed=3), approach([80.0, 440.0], seed=4)
    catalog.add_episode(train, split="train")
    catalog.add_episode(held_out, split="eval")
    return catalog, train, held_out


@pytest.mark.parametrize("replay_prefix", [True, False])
def test_no_request_is_built_from_an_eval_episode(catalog_with_both, replay_prefix):
    catalog, train, held_out = catalog_with_both
    cfg = ActivePlannerConfig(percentile=0.0, budget_per_round=8, max_queue_depth=64, max_shape_share=1.0,
                              replay_prefix=replay_prefix)
    is_eval = in_eval_split(catalog)
    assert is_eval(held_out.meta.episode_id) and not is_eval(train.meta.episode_id)
    assert not is_eval("not-in-the-catalog")

    def scorer(ep: Episode) -> Scores:  # the eval episode scores far higher: it would take the whole round
        return Scores("m1", pusher_speed(ep).per_step + (1000.0 if ep is held_out else 0.0))

    unguarded = ActivePlanner(cfg, scorer, np.random.default_rng(0)).plan([held_out, train])
    assert unguarded and unguarded[0].reason["source_episode"] == held_out.meta.episode_id
    planner = ActivePlanner(cfg, scorer, np.random.default_rng(0), is_eval=is_eval)
    assert planner.plan([held_out]) == []
    reqs = planner.plan([held_out, train])
    assert reqs and {r.reason["source_episode"] for r in reqs} == {train.meta.episode_id}
    if replay_prefix:
        assert all(r.start_state == train.meta.start_state for r in reqs)
    # before any champion, an eval episode is not replaced by a uniform request either (it was not collected)
    assert ActivePlanner(cfg, lambda ep: None, np.random.default_rng(0), is_eval=is_eval).plan([held_out]) == []


def test_serves_active_planner_knows_the_catalogs_eval_episodes(catalog_with_both, tmp_path):
    from orchestrator.cli.service import planner_factory
    from orchestrator.metrics import ServiceMetrics
    from orchestrator.protocol import Keys
    from orchestrator.serviceconfig import ServiceContext
    from storage.models import ModelRegistry
    from storage.queue import RequestQueue
    catalog, train, held_out = catalog_with_both
    ctx = ServiceContext(catalog.data_dir, Keys("t"), RequestQueue(catalog.db_path), catalog,
                         ModelRegistry(catalog.data_dir), ServiceMetrics(), lambda kind, body: None)
    planner = planner_factory("active", 20, 0)(ctx)
    assert planner.is_eval(held_out.meta.episode_id) and not planner.is_eval(train.meta.episode_id)
