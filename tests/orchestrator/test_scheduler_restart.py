"""A scheduled retrain that a restart of the service must not lose: one stopped before its gate (while starting, or
between its register and its gate), a multiple of --retrain-every crossed while no service ran, and a trigger whose
launch could not count the episodes."""

from __future__ import annotations

import json
import logging
import os
import pathlib

import pytest

from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.retrainlock import JOB_ENV, note_phase, retrain_lock
from orchestrator.scheduler import RetrainScheduler
from storage.errors import StorageUnavailableError
from storage.models import ModelRegistry
from tests.orchestrator.test_scheduler import HANGS, PROMOTES, Counter, script_command


def test_a_job_stopped_with_the_service_before_its_gate_runs_again_at_the_next_start(tmp_path):
    """Stopped while still starting (before it took the retrain lock, whose notes are then an earlier job's):
    the restarted service counted from the episodes it found and ran nothing until the next multiple."""
    episodes = Counter()
    sched = RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, episodes, command=script_command(HANGS))
    episodes.n = 5
    rec = sched.tick()
    sched.stop(kill_running=True)
    assert rec.status is RetrainStatus.killed
    again = RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, episodes, command=script_command(PROMOTES))
    rerun = again.tick()
    assert rerun is not None and rerun.trigger == "episodes"
    assert again.wait_idle(timeout=60) and rerun.status is RetrainStatus.promoted
    assert RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, episodes,
                            command=script_command(PROMOTES)).tick() is None  # done: not once more


def test_a_multiple_crossed_while_no_service_ran_is_retrained_at_the_next_start(tmp_path):
    episodes = Counter()
    sched = RetrainScheduler(ScheduleConfig(every_episodes=10), tmp_path, episodes, command=script_command(PROMOTES))
    episodes.n = 10
    assert sched.tick() is not None and sched.wait_idle(timeout=60)
    sched.stop()
    episodes.n = 21  # the last uploads of a stop, an offline ingest: 20 crossed with no scheduler counting
    again = RetrainScheduler(ScheduleConfig(every_episodes=10), tmp_path, episodes, command=script_command(PROMOTES))
    rec = again.tick()
    assert rec is not None and rec.trigger == "episodes" and rec.episodes == 21
    assert again.wait_idle(timeout=60)


def test_a_trigger_whose_launch_could_not_count_the_episodes_is_tried_at_the_next_tick(tmp_path):
    """A daily cron whose one catalog read at its time failed waited a day."""
    failing = [False]

    def count() -> int:
        if failing[0]:
            failing[0] = False
            raise StorageUnavailableError("database is locked")
        return 10

    sched = RetrainScheduler(ScheduleConfig(cron="0 3 * * *"), tmp_path, count, command=script_command(PROMOTES))
    due = sched._next_cron
    failing[0] = True
    with pytest.raises(StorageUnavailableError):
        sched.tick(now=due + 1)
    rec = sched.tick(now=due + 2)
    assert rec is not None and rec.trigger == "cron" and sched.wait_idle(timeout=60)
    assert not pathlib.Path(tmp_path, "retrain.due").exists()  # (a job that ended leaves no mark)


def test_a_start_beside_a_live_holder_of_the_retrain_lock_says_so_not_that_it_died(tmp_path, caplog, monkeypatch):
    """A job a SIGKILLed service left stopped (SIGSTOP) keeps the lock: the next start said the job 'died' and every
    scheduled retrain then waited on the lock without a word."""
    monkeypatch.setenv(JOB_ENV, "job-1")  # (what the scheduler gives its jobs)
    (tmp_path / "retrain.due").write_text("{}")  # (the dead service's mark of its job: said after the lock's holder)
    with retrain_lock(tmp_path):
        note_phase(tmp_path, "training")
        with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
            RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, Counter(), command=script_command(PROMOTES))
    said = " ".join(r.getMessage() for r in caplog.records)
    assert f"the retrain lock is held by pid {os.getpid()}" in said and "died" not in said, said


@pytest.mark.parametrize("phase, gated, again", [(None, False, True), ("registered", False, True),
                                                 ("registered", True, False), ("done", True, False),
                                                 ("failed", False, False)],
                         ids=["starting", "before-its-gate", "gated", "done", "failed-by-itself"])
def test_a_job_the_services_death_left_unreaped_runs_again_only_if_it_had_not_passed_its_gate(tmp_path, phase, gated,
                                                                                             again):
    """The service SIGKILLed after a job's gate had decided (before it reaped the job) left the mark, and the next
    start retrained once more, saying the job was stopped before its gate (a review's reproduction)."""
    registry = ModelRegistry(tmp_path)
    version = registry.register(b"w", {}, {"h1_mse": 0.01}, snapshot_id="s", eval_split_hash="h")
    if gated:
        registry.gate(version)
    notes = tmp_path / "logs" / "retrain-x.log.notes"
    notes.parent.mkdir()
    if phase is not None:
        notes.write_text(json.dumps({"pid": 1, "phase": phase, "job": "j", **({"version": version} if phase in
                                                                              ("registered", "done") else {})}))
    (tmp_path / "retrain.due").write_text(json.dumps({"trigger": "episodes", "notes": str(notes)}))
    sched = RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, Counter(), command=script_command(PROMOTES))
    rec = sched.tick()
    assert (rec is not None) == again
    assert sched.wait_idle(timeout=60)
    assert not (tmp_path / "retrain.due").exists()
