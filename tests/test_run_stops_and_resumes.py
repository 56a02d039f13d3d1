"""``activecollect run``: stop signals once the loop is over, finished data directories with a lost or quarantined
episode, a round whose retrain found the retrain lock held, and what the report says of an interrupted run.

Real processes, real SQLite and real files: a small finished data directory (an eval split, a few 16 px training
episodes and a model trained on them, as an earlier run leaves it), then ``LoopRun`` on it with its service, worker
processes over Zenoh on loopback and retrain jobs. A signal at a precise phase is sent from a wrapped function.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import orchestrator.loop
from orchestrator.loop import LoopRun
from orchestrator.loopconfig import RunConfig
from orchestrator.retrainlock import retrain_lock
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from storage.catalog import Catalog
from storage.models import ModelRegistry
from tests.conftest import wait_for
from tests.test_run import train_count

STEPS, SIZE = 8, 16
#: A 1-epoch retrain of a tiny model, as ``run --retrain-args`` gives it.
RETRAIN_ARGS = ("--members", "2", "--epochs", "1", "--widths", "4,4,4", "--batch-size", "8", "--from-champion",
                "--device", "cpu", "--min-improvement", "0")
STILL_TO_WRITE = "Ctrl-C: stopping already; a running retrain is stopped, the rest of the stop is not cut short"


def make_split(catalog, episodes, seed, steps, size):
    from workers.collect import create_eval_split
    return create_eval_split(catalog, episodes, seed, steps, size)


def config(data: Path, budget: int) -> RunConfig:
    return RunConfig(data_dir=data, budget=budget, round_episodes=2, workers=1, steps=STEPS, image_size=SIZE,
                     eval_episodes=2, dashboard_port=-1, progress=False, retrain_args=RETRAIN_ARGS)


def finished_dir(data: Path, episodes: int = 4, quarantined: int = 0) -> Catalog:
    """What a run with a budget of ``episodes`` leaves: the eval split, ``episodes`` training episodes, and a model
    trained on them; the first ``quarantined`` of them quarantined before it trained (lost files its retrain found)."""
    from uncertainty.config import TrainConfig
    from uncertainty.train import train_candidate
    from workers.collect import collect_episode
    catalog = Catalog(data)
    make_split(catalog, 2, RunConfig.eval_seed, STEPS, SIZE)
    planner = UniformPlanner(UniformPlannerConfig(steps=STEPS), np.random.default_rng(0))
    ids = [catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy,
                                               policy_params=r.policy_params, seed=i, steps=STEPS,
                                               image_size=SIZE)).episode_id
           for i, r in enumerate(planner.seed(episodes))]
    for episode_id in ids[:quarantined]:
        catalog.quarantine(episode_id, "found by a training job: its file is missing")
    train_candidate(catalog, ModelRegistry(data), TrainConfig(members=2, widths=(4, 4, 4), batch_size=8, epochs=1,
                                                              device="cpu", progress=False))
    return catalog


def signal_then(real, sigint_count: list[int], caplog):
    """``real``, called after a SIGINT to this process has been taken (one more "still to be written" line)."""
    def wrapped(*args, **kwargs):
        sigint_count[0] += 1
        os.kill(os.getpid(), signal.SIGINT)
        wait_for(lambda: caplog.text.count(STILL_TO_WRITE) >= sigint_count[0], message="the run to take the Ctrl-C")
        return real(*args, **kwargs)
    return wrapped


def test_ctrl_c_during_the_tear_down_and_the_report_of_an_interrupted_run_still_gets_its_report(tmp_path, monkeypatch,
                                                                                                caplog):
    """Ctrl-C in set-up, then again while the workers stop and while the report is written (a user pressing it
    again, or twice): each later one is logged, and the report is written whole. The old run raised
    KeyboardInterrupt out of its tear-down: no report, an empty reports/<time>/ folder."""
    def interrupted_eval_split(catalog, episodes, seed, steps, size):
        raise KeyboardInterrupt

    sent = [0]
    monkeypatch.setattr(LoopRun, "_teardown", signal_then(LoopRun._teardown, sent, caplog))
    monkeypatch.setattr(orchestrator.loop, "write_report", signal_then(orchestrator.loop.write_report, sent, caplog))
    data = tmp_path / "data"
    with caplog.at_level(logging.WARNING, logger="orchestrator.loop"):
        result = LoopRun(config(data, 4), interrupted_eval_split).run()
    assert result.interrupted and result.report.is_file() and caplog.text.count(STILL_TO_WRITE) == 2
    assert [p.name for p in (data / "reports").iterdir()] == [result.report.parent.name]  # (no folder left aside)
    assert {"index.html", "summary.json", "curve.png"} <= {p.name for p in result.report.parent.iterdir()}
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # given back


def test_a_report_cut_short_leaves_no_report_folder(tmp_path, monkeypatch):
    """A report whose writing fails half-way (here its page) leaves no reports/<time>/ folder without a page in
    it: it is written aside and renamed into place whole."""
    import orchestrator.report
    from orchestrator.report import ReportInputs, write_report

    def fails(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(orchestrator.report, "_html", fails)
    with pytest.raises(OSError):
        write_report(tmp_path, ReportInputs(curve=[], summary={"episodes": 0}))
    assert list((tmp_path / "reports").iterdir()) == []
    monkeypatch.undo()
    killed = tmp_path / "reports" / ".20010909T014639-99999.tmp"  # what a writer SIGKILLed midway leaves
    (killed / "curve.png").parent.mkdir()
    (killed / "curve.png").write_bytes(b"half")
    first = write_report(tmp_path, ReportInputs(curve=[], summary={"episodes": 0}), when=1e9)
    second = write_report(tmp_path, ReportInputs(curve=[], summary={"episodes": 0}), when=1e9)
    assert (first.parent.name, second.parent.name) == ("20010909T014640", "20010909T014640-1")
    assert sorted(p.name for p in (tmp_path / "reports").iterdir()) == [first.parent.name, second.parent.name]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_finished_directory_with_a_quarantined_episode_stops_at_once_and_ctrl_c_does_not_cut_its_report(
        tmp_path, monkeypatch, caplog):
    """The retrain that quarantined a lost file trained on the others: a run over the finished directory (its
    budget counts the quarantined episode, as the catalog's) trains nothing more. The old run compared the
    model's count without the quarantined episode with the catalog's with it and retrained on every run.
    A Ctrl-C while its report is written leaves the report whole and the run done, not interrupted."""
    data = tmp_path / "data"
    finished_dir(data, episodes=4, quarantined=1)
    models = len(ModelRegistry(data).list())
    sent = [0]
    monkeypatch.setattr(orchestrator.loop, "write_report", signal_then(orchestrator.loop.write_report, sent, caplog))
    with caplog.at_level(logging.WARNING, logger="orchestrator.loop"):
        result = LoopRun(config(data, 4), make_split).run()
    assert (result.episodes, result.collected, result.retrains, result.interrupted) == (4, 0, [], False)
    assert len(ModelRegistry(data).list()) == models and caplog.text.count(STILL_TO_WRITE) == 1
    summary = json.loads((result.report.parent / "summary.json").read_text())["summary"]
    assert (summary["episodes"], summary["quarantined"]) == (4, 1)
    assert "<th>of those, quarantined (not trained on)</th><td>1</td>" in result.report.read_text()


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_lost_training_file_is_quarantined_by_the_run_which_reports_and_resumes(tmp_path, caplog):
    """A training episode's file is gone (not quarantined yet): the run over the finished directory writes its
    report without it, and a run resumed to a larger budget plans its next round without the next lost one;
    each is quarantined as a retrain would. The old run raised the catalog's error in both (exit 1)."""
    data = tmp_path / "data"
    catalog = finished_dir(data, episodes=4)
    newest = catalog.list(split="train", newest_first=True)
    newest[0].path.unlink()
    with caplog.at_level(logging.WARNING, logger="orchestrator.loop_catalog"):
        result = LoopRun(config(data, 4), make_split).run()
    assert (result.episodes, result.retrains, result.interrupted) == (4, [], False) and result.report.is_file()
    assert catalog.get(newest[0].episode_id).quarantined and f"episode {newest[0].episode_id} quarantined and " \
        "left out of the report: " in caplog.text

    newest[1].path.unlink()  # the next round is planned from the newest round: this one among them
    result = LoopRun(config(data, 6), make_split).run()
    assert (result.episodes, result.collected, result.interrupted) == (6, 2, False) and result.report.is_file()
    assert catalog.get(newest[1].episode_id).quarantined and "left out of the next round's plan: " in caplog.text
    assert [r["status"] in ("promoted", "rejected") for r in result.retrains] == [True]


def test_a_run_over_a_disk_not_mounted_quarantines_nothing(tmp_path, caplog):
    """Most training files missing at once (the episodes' disk not mounted): left out of the report, none
    quarantined, as a retrain does; once the disk is back they train again (the old run quarantined them all)."""
    data = tmp_path / "data"
    catalog = finished_dir(data, episodes=4)
    (data / "episodes").rename(data / "episodes.away")
    (data / "episodes").mkdir()
    with caplog.at_level(logging.WARNING, logger="orchestrator.loop_catalog"):
        result = LoopRun(config(data, 4), make_split).run()
    assert result.report.is_file() and not result.interrupted
    assert catalog.count(split="train", quarantined=True) == 0
    assert "the files of 4 of 4 episodes loaded for the report are missing or damaged" in caplog.text
    assert "nothing quarantined" in caplog.text


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_round_whose_retrain_found_the_lock_held_is_retrained_once_it_is_free(tmp_path):
    """Another retrain (a cron job's) holds DATA/retrain.lock when the last round's retrain starts: the run waits
    for the lock and then retrains the round. The old run took the busy job for the round's retrain and ended
    "done" with the last round never trained."""
    data = tmp_path / "data"
    cmd = [sys.executable, "-m", "orchestrator", "run", "--data", str(data), "--budget", "2", "--round", "2",
           "--workers", "1", "--steps", str(STEPS), "--image-size", str(SIZE), "--eval-episodes", "1",
           "--dashboard-port", "-1", "--no-progress", "--json", "--retrain-args", " ".join(RETRAIN_ARGS)]
    with retrain_lock(data):
        run = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            wait_for(lambda: any("another retrain holds" in p.read_text() for p in (data / "logs").glob(
                "retrain-*.log")) or run.poll() is not None, 240, "the round's retrain to find the lock held")
        except BaseException:
            run.kill()
            raise
    out, err = run.communicate(timeout=240)
    assert run.returncode == 0, err[-3000:]
    result = json.loads(out)
    assert [r["status"] for r in result["retrains"]][0] == "busy" and len(result["retrains"]) == 2, err[-3000:]
    assert result["retrains"][1]["status"] in ("promoted", "rejected") and result["retrains"][1]["episodes"] == 2
    assert max(int(m.metrics["train_episodes"]) for m in ModelRegistry(data).list()) == 2 == train_count(data)


@pytest.mark.parametrize("when, headline", [
    ("set-up", "Interrupted (Ctrl-C or SIGTERM) during set-up: "),
    ("collection", "Interrupted (Ctrl-C or SIGTERM) before the budget was spent: "),
    ("the last retrain", "Interrupted (Ctrl-C or SIGTERM) with the budget spent, before its last retrain: "),
])
def test_the_headline_of_an_interrupted_run_says_what_was_left(tmp_path, when, headline):
    """The old headline said "before the budget was spent" also of a run stopped during its last retrain."""
    from orchestrator.report import ReportInputs, write_report
    summary = {"episodes": 8, "collected_this_run": 8, "budget": 8, "interrupted": True, "interrupted_in": when}
    page = write_report(tmp_path, ReportInputs(curve=[], summary=summary)).read_text()
    assert f"<p>{headline}the next run on this data directory resumes from its catalog.</p>" in page


def test_the_run_says_which_eval_episodes_are_left_outside_its_split(tmp_path, caplog):
    """An interrupted eval split taken up with fewer --eval-episodes leaves eval episodes outside the split:
    `run` says so, as `eval-split create` does (one check for both). The old run said nothing."""
    from workers.collect import collect_episode, eval_split_plan, EVAL_POLICY
    data = tmp_path / "data"
    catalog = Catalog(data)
    for i, (seed, start) in enumerate(eval_split_plan(3, RunConfig.eval_seed, False)):  # what the create indexed
        catalog.add_episode(collect_episode(start_state=start, policy=EVAL_POLICY, seed=seed, steps=STEPS,
                                            image_size=SIZE), split="eval")

    def interrupted_after_the_split(catalog, episodes, seed, steps, size):
        digest = make_split(catalog, episodes, seed, steps, size)
        os.kill(os.getpid(), signal.SIGTERM)  # (stop before any worker starts)
        wait_for(lambda: run._terminated.is_set(), message="the run to take the SIGTERM")
        return digest

    run = LoopRun(config(data, 4), interrupted_after_the_split)
    with caplog.at_level(logging.WARNING, logger="orchestrator.loop"):
        result = run.run()
    left = catalog.count(split="eval") - len(catalog.eval_split().ids)
    assert result.interrupted and left > 0
    assert f"{left} eval episode(s) in {catalog.data_dir} are not in the split" in caplog.text
