"""Scheduled retrains run again when the trigger found the retrain lock busy, or when the last one died midway."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.retrainlock import read_lock_info, retrain_lock
from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from tests.conftest import wait_for
from tests.orchestrator.test_scheduler import PROMOTES, Counter, script_command


#: A job that takes the retrain lock as the real one does: exit 3 (busy) while another holds it, else promote.
LOCKS_THEN_PROMOTES = (
    "import json, pathlib, sys\n"
    "from orchestrator.retrainlock import RetrainBusyError, retrain_lock\n"
    "try:\n"
    "    with retrain_lock(pathlib.Path(sys.argv[1])):\n"
    f"        {PROMOTES}\n"
    "except RetrainBusyError:\n"
    "    sys.exit(3)\n")


@pytest.mark.parametrize("trigger", ["episodes", "cron"])
def test_a_scheduled_retrain_that_found_the_lock_busy_runs_once_it_is_free(tmp_path, trigger):
    """An operator's `activecollect retrain` (or system cron's) holds the lock when the schedule fires: the job
    exits busy, and the schedule's retrain runs as soon as the lock is free, not at the next trigger (N more
    episodes, or the next day on a daily cron). The old scheduler spent the trigger on the busy job."""
    episodes = Counter()
    cfg = ScheduleConfig(every_episodes=5) if trigger == "episodes" else ScheduleConfig(cron="0 3 * * *")
    sched = RetrainScheduler(cfg, tmp_path, episodes, command=script_command(LOCKS_THEN_PROMOTES))
    with retrain_lock(tmp_path):
        episodes.n = 5
        busy = sched.tick(now=sched._next_cron + 1 if trigger == "cron" else None)
        assert busy is not None and busy.trigger == trigger
        assert sched.wait_idle(timeout=60) and busy.status is RetrainStatus.busy, busy.reason
        assert sched.tick() is None  # the lock is still held: nothing is started
    rec = sched.tick()
    assert rec is not None and rec.trigger == trigger
    assert sched.wait_idle(timeout=60) and rec.status is RetrainStatus.promoted, rec.reason
    assert sched.tick() is None  # once, not again


def test_a_requested_retrain_that_found_the_lock_busy_is_not_repeated(tmp_path):
    """A retrain someone asked for (`run`'s rounds, the admin's `retrain`) sees its busy record and decides."""
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(LOCKS_THEN_PROMOTES))
    with retrain_lock(tmp_path):
        sched.request("round")
        busy = sched.tick()
        assert sched.wait_idle(timeout=60) and busy.status is RetrainStatus.busy
    assert sched.tick() is None


def _job_dies_while(data_dir: Path, phase: str) -> None:
    """A retrain the scheduler started (its job id in the environment) takes the lock, notes ``phase``, and is
    SIGKILLed there: what a service's stop or a crash in the middle of a job leaves in the lock file."""
    code = ("import pathlib, sys, time\n"
            "from orchestrator.retrainlock import note_phase, retrain_lock\n"
            "with retrain_lock(pathlib.Path(sys.argv[1])):\n"
            f"    note_phase(pathlib.Path(sys.argv[1]), {phase!r})\n"
            "    time.sleep(600)\n")
    job = subprocess.Popen([sys.executable, "-c", code, str(data_dir)],
                           env={**os.environ, "ACTIVECOLLECT_RETRAIN_JOB": "0123456789abcdef"})
    try:
        wait_for(lambda: read_lock_info(data_dir).get("phase") == phase, timeout=30, message="the job's phase")
    finally:
        job.kill()
        job.wait()


@pytest.mark.parametrize("phase, again", [("training", True), ("done", False)])
def test_a_scheduled_retrain_that_died_midway_runs_again_when_the_service_starts_again(tmp_path, phase, again):
    """`serve` was stopped (or crashed) while its retrain trained: the next `serve` runs that retrain at once, not
    at the next trigger. A job that finished (phase done) is not repeated. The old scheduler never noticed."""
    _job_dies_while(tmp_path, phase)
    episodes = Counter()
    episodes.n = 7
    sched = RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, episodes, command=script_command(PROMOTES))
    rec = sched.tick()
    assert (rec is not None) == again
    if again:
        assert rec.trigger == "episodes" and sched.wait_idle(timeout=60) and rec.status is RetrainStatus.promoted
    assert sched.tick() is None


def test_a_died_job_is_not_repeated_without_a_schedule(tmp_path):
    """`run` asks for its rounds itself (no schedule of episodes or cron): nothing is started on its behalf."""
    _job_dies_while(tmp_path, "training")
    assert RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(PROMOTES)).tick() is None
