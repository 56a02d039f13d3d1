"""``activecollect run`` resumed after a crash: the budget holds, the leftover queue is reused or cancelled, the
report tells the runs apart, and ``--json`` is strict JSON.

Real processes throughout: a run SIGKILLed with its workers (a power cut, an OOM kill of the group), then the next
run on the same directory, as an operator would start it.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
from pathlib import Path

import pytest

from storage.catalog import Catalog
from storage.queue import RequestQueue
from tests.conftest import run_cli, wait_for
from tests.test_run import run_cmd, train_count


def strict_json(text: str) -> object:
    def refuse(constant: str) -> None:
        raise ValueError(f"not strict JSON: {constant}")
    return json.loads(text, parse_constant=refuse)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_run_killed_mid_round_is_resumed_within_the_next_runs_budget_and_reported_as_resumed(tmp_path):
    """The killed run had queued a whole round (12 requests); the next run with a budget of 2 more episodes collected
    every one of them before it stopped (the loop waits for the queue to empty), 10 past its budget."""
    data = tmp_path / "data"
    first = subprocess.Popen(run_cmd(data, 400) + ["--round", "12"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        wait_for(lambda: train_count(data) >= 1, 120, "the first uploads")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(first.pid, signal.SIGKILL)  # the run and its workers at once
        first.wait()
    kept = train_count(data)
    with RequestQueue(data / "catalog.sqlite") as queue:
        left = queue.counts()
    assert left["queued"] + left["leased"] + kept == 12, left  # the rest of the killed run's round
    assert left["queued"] > 2, left

    budget = kept + 2
    second = subprocess.run(run_cmd(data, budget) + ["--round", "12"], capture_output=True, text=True, timeout=240)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "cancelled" in second.stderr and "queued request(s) left by an earlier run" in second.stderr
    result = strict_json(second.stdout)
    assert (result["episodes"], result["collected"]) == (budget, 2) and train_count(data) == budget
    catalog = Catalog(data)
    with RequestQueue(catalog.db_path) as queue:
        counts = queue.counts()
        done = queue.list(status="done")
    assert counts["queued"] == counts["leased"] == 0 and counts["done"] == budget, counts
    assert counts["cancelled"] == 12 - budget, counts  # the rest of the round, past the budget: not collected
    assert all(catalog.get(r.episode_id).request_id == r.id for r in done)  # nothing acknowledged is lost

    report = Path(result["report"])
    summary = strict_json((report.parent / "summary.json").read_text())["summary"]
    assert (summary["episodes"], summary["collected_this_run"]) == (budget, 2)
    html = report.read_text()
    assert f"This run collected 2 of the catalog&#x27;s {budget} training episodes" in html
    assert "<th>training episodes (catalog)</th>" in html and "<th>retrains (this run)</th>" in html


def test_bench_loop_json_is_strict_when_episodes_are_too_short_for_h5(tmp_path, capsys):
    """Episodes of 5 steps have no 5-step error to measure (NaN): --json printed a bare NaN, which jq refuses."""
    rc, out, err = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "4", "--round", "2", "--steps", "5",
                           "--image-size", "16", "--epochs", "1", "--members", "2", "--json",
                           "--out", str(tmp_path / "loop"))
    assert rc == 0, err[-2000:]
    summary = strict_json(out)
    assert [p["h5_mse"] for p in summary["points"]] == [None] * 4
    assert all(isinstance(p["h1_mse"], float) for p in summary["points"])
    assert strict_json((tmp_path / "loop" / "summary.json").read_text()) == summary  # the file the same


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_run_json_is_strict_when_episodes_are_too_short_for_h5(tmp_path):
    """A run of 5-step episodes: its retrains' h5 and h10 errors cannot be measured (NaN) and --json printed them
    bare."""
    proc = subprocess.run(run_cmd(tmp_path / "data", 2) + ["--round", "2", "--workers", "1", "--steps", "5"],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = strict_json(proc.stdout)
    metrics = result["retrains"][0]["metrics"]
    assert metrics["h5_mse"] is None and isinstance(metrics["h1_mse"], float)


def test_a_candidate_whose_job_died_before_its_gate_does_not_count_as_the_rounds_retrain(tmp_path):
    """A run SIGKILLed while its last retrain was between register and gate leaves a candidate that trained on the
    whole budget; the next run counted it as that retrain, stopped at once, and reported the model before it."""
    import numpy as np

    from orchestrator.loop import LoopRun
    from orchestrator.loopconfig import RunConfig
    from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
    from storage.models import ModelRegistry
    from workers.collect import collect_episode, create_eval_split

    data = tmp_path / "data"
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=1, seed=RunConfig.eval_seed, steps=8, image_size=16)
    for i, r in enumerate(UniformPlanner(UniformPlannerConfig(steps=8), np.random.default_rng(0)).seed(2)):
        catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy, policy_params=r.policy_params,
                                            seed=i, steps=8, image_size=16))
    registry = ModelRegistry(data)
    left = registry.register(b"never gated", {}, {"h1_mse": 0.01, "train_episodes": 2}, snapshot_id="s",
                             eval_split_hash=catalog.eval_split().hash)
    cfg = RunConfig(data_dir=data, budget=2, round_episodes=2, workers=1, steps=8, image_size=16, eval_episodes=1,
                    dashboard_port=-1, progress=False, retrain_args=("--members", "2", "--epochs", "1", "--widths",
                                                                     "4,4,4", "--device", "cpu"))
    result = LoopRun(cfg, create_eval_split).run()
    assert [r["status"] for r in result.retrains] == ["promoted"] and result.collected == 0
    assert result.champion not in (None, left) and registry.get(left).status.value == "rejected"


@pytest.mark.parametrize("field, value", [("zenoh_port", -1), ("zenoh_port", 65536), ("lease_s", 0.0),
                                          ("lease_s", float("nan")), ("retrain_timeout_s", -1.0)])
def test_run_config_refuses_ports_and_times_out_of_range(tmp_path, field, value):
    from orchestrator.loopconfig import RunConfig
    with pytest.raises(ValueError, match=f"^{field} must be "):
        RunConfig(data_dir=tmp_path, **{field: value})
