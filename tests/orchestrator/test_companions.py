"""``serve``'s companions: the scheduler retrains on new episodes in a child process and the
dashboard reports the promoted champion, beside a real service."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request

import numpy as np
import pytest

from orchestrator.champion import ChampionScorer
from orchestrator.cli.service import planner_factory
from orchestrator.companions import CompanionConfig, Companions
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage.models import ModelRegistry
from tests.conftest import free_port, wait_for
from workers.collect import collect_episode, create_eval_split

TINY = ("--members", "2", "--widths", "4,4,4", "--batch-size", "8", "--device", "cpu",
        "--min-improvement", "0", "--epochs", "1")


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as reply:
        return reply.read()


def test_config_is_validated():
    with pytest.raises(ValueError, match="dashboard_port"):
        CompanionConfig(dashboard_port=-2)
    with pytest.raises(ValueError, match="retrain_every"):
        CompanionConfig(retrain_every=-1)
    with pytest.raises(ValueError, match="cron"):
        CompanionConfig(retrain_cron="every minute")


def test_serve_refuses_a_bad_schedule_before_touching_anything(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "orchestrator", "serve", "--data", str(tmp_path / "d"),
                           "--retrain-cron", "every minute"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "cron" in proc.stderr
    assert not (tmp_path / "d").exists()


def test_new_episodes_trigger_a_retrain_and_the_dashboard_shows_the_champion(data_dir, endpoint, namespace):
    service = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,)))
    companions = Companions(CompanionConfig(dashboard_port=0, retrain_every=3, retrain_args=TINY), service)
    service.start()
    try:
        companions.start()
        catalog = service.context.catalog
        create_eval_split(catalog, episodes=4, seed=1, steps=12, image_size=16)
        planner = UniformPlanner(UniformPlannerConfig(steps=12), np.random.default_rng(0))
        for i, r in enumerate(planner.seed(3)):
            catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy,
                                                policy_params=r.policy_params, seed=i, steps=12, image_size=16))
        champion = wait_for(lambda: ModelRegistry(data_dir).champion(), timeout=240, message="a champion")
        url = companions.dashboard.url
        stats = wait_for(lambda: json.loads(_get(url + "api/stats")), message="stats")
        assert champion in json.dumps(stats)
        metrics = wait_for(lambda: (m := _get(url + "metrics").decode()) and
                           'retrains_total{outcome="promoted"} 1.0' in m and m, timeout=30,
                           message="the retrain counted in /metrics")
        assert "queue_depth" in metrics
        assert companions.scheduler.history[0].trigger == "episodes"
    finally:
        companions.stop()
        service.stop()


def test_the_dashboard_draws_with_the_planners_champion_scorer_so_the_champion_is_loaded_once(tmp_path, namespace):
    for name in ("active", "uniform"):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        service = Service(ServiceConfig(data_dir=tmp_path / name, namespace=namespace, listen=(endpoint,),
                                        planner=planner_factory(name, steps=12, seed=0, threads=1)))
        companions = Companions(CompanionConfig(dashboard_port=0, scoring_threads=1), service)
        service.start()
        try:
            companions.start()
            assert isinstance(companions.scorer, ChampionScorer) and companions.scorer.threads == 1
            assert (companions.scorer is getattr(service.planner, "scorer", None)) == (name == "active")
            assert _get(companions.dashboard.url + "api/stats")  # it serves
        finally:
            companions.stop()
            service.stop()
