"""The active planner's memory of what it requested (``ActivePlannerConfig.memory``): bounded, as a service that
runs unattended for months needs, and within the bound no state is requested twice."""

from __future__ import annotations

import dataclasses

import numpy as np

from orchestrator.planner import ActivePlanner
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from tests.orchestrator.test_planner import acfg, make_episode, step_scorer


def test_the_planner_remembers_its_last_requests_only_and_never_repeats_one_of_them():
    rng = np.random.default_rng(30)
    cfg = acfg(percentile=0.0, budget_per_round=2, min_distance=0.0, memory=6, max_queue_depth=1000)
    planner = ActivePlanner(cfg, step_scorer(), rng)
    ep = make_episode(rng, steps=20)
    steps = lambda reqs: [r.reason["step"] for r in reqs]  # noqa: E731 (the score is the step: highest first)
    assert steps(planner.plan([ep])) == [19, 18]
    other = planner.plan([make_episode(rng, steps=20)])
    assert len(other) == 2
    # within the memory (4 of 6 requests so far) the same episode gives its next states, not the same ones
    assert steps(planner.plan([ep])) == [17, 16]
    for _ in range(300):  # a long-running service: a new episode at a time
        assert len(planner.plan([make_episode(rng, steps=20)])) == 2
    assert len(planner._requested_steps) <= cfg.memory and len(planner._requested) <= cfg.memory
    # the old requests are forgotten: the queue's idempotency key (the same for the same state) refuses them
    again = planner.plan([ep])
    assert steps(again) == [19, 18] and again[0].idempotency_key == f"active:{ep.meta.episode_id}:19"


def test_serves_planner_remembers_the_queues_requests_across_a_restart(tmp_path):
    """An episode collected at a requested pose holds it (at rest) while its new pusher approaches; a restarted
    service's planner used to ask for that very pose again (its key names the new episode)."""
    from orchestrator.cli.service import planner_factory
    from orchestrator.metrics import ServiceMetrics
    from orchestrator.protocol import Keys
    from orchestrator.serviceconfig import ServiceContext
    from storage.catalog import Catalog
    from storage.models import ModelRegistry
    from storage.queue import RequestQueue

    rng = np.random.default_rng(31)
    catalog = Catalog(tmp_path / "data")
    queue = RequestQueue(catalog.db_path)
    ctx = ServiceContext(catalog.data_dir, Keys("t"), queue, catalog, ModelRegistry(catalog.data_dir),
                         ServiceMetrics(), lambda kind, body: None)
    source = make_episode(rng, steps=20, jitter=0.0)  # one pose throughout, as a follow-up's approach holds it

    def restarted():
        planner = planner_factory("active", 20, 0)(ctx)
        planner.cfg = dataclasses.replace(planner.cfg, task_space_only=False, percentile=0.0)
        planner.scorer = step_scorer()
        return planner

    first = restarted().plan([source])
    assert len(first) == 1 and all(queue.enqueue(r)[1] for r in first)
    follow_up = dataclasses.replace(source, meta=dataclasses.replace(source.meta, episode_id="follow-up"))
    assert restarted().plan([follow_up]) == []  # the same pose: asked for already
    uniform = UniformPlanner(UniformPlannerConfig(), rng)
    for _ in range(300):  # more top-ups since than the memory holds, each gone by now (below the depth cap)
        queue.cancel(queue.enqueue(uniform.seed(1)[0])[0].id)
    assert restarted().plan([follow_up]) == []  # (the latest 256 of every planner's held no active one)
    assert restarted().plan([make_episode(rng, steps=20)])  # a new pose is asked for
