"""The window between a retrain job's end and the scheduler's reap of it (up to ``poll_s``): the job has released
``DATA/retrain.lock``, and another retrain (system cron, one by hand) may take it and write its own notes there
before the scheduler reads what the dead job left. The job's own notes file keeps them."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

from orchestrator.retrainlock import note_phase, read_lock_info, retrain_lock
from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from storage.models import ModelRegistry
from tests.conftest import wait_for

#: A job that registers a model with h1_mse 0.01 and gates it under the lock, as ``activecollect retrain`` does,
#: writes the version to DATA/gated, then fails (``crash``: a prune on a broken disk) or hangs (``hang``).
GATES = """
import pathlib, sys, time
from orchestrator.retrain import training_job
data, then = pathlib.Path(sys.argv[1]), sys.argv[2]
with training_job(data) as (catalog, registry, abandoned):
    version = registry.register(b'weights of this job', {}, {'h1_mse': 0.01}, 'snap', 'split')
    registry.gate(version)
    pathlib.Path(data, 'gated').write_text(version)
    if then == 'crash':
        raise RuntimeError('the disk went away while pruning')
    time.sleep(600)
"""


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """A registry whose champion has h1_mse 0.02."""
    registry = ModelRegistry(tmp_path)
    assert registry.gate(registry.register(b"the champion's weights", {}, {"h1_mse": 0.02}, "snap", "split")).promoted
    return tmp_path


@pytest.mark.parametrize("ending", ["crash", "sigkill"])
def test_a_promotion_is_the_dead_jobs_though_another_retrain_took_the_lock_before_the_reap(data, ending):
    promoted, finished = [], []
    sched = RetrainScheduler(ScheduleConfig(), data, lambda: 0, promoted.append, on_finished=finished.append,
                             command=lambda d, extra: [sys.executable, "-c", GATES, str(d), ending])
    sched.request()
    assert sched.tick() is not None  # no scheduler thread: the test decides when the reap comes
    version = wait_for(lambda: (data / "gated").is_file() and (data / "gated").read_text(), timeout=60,
                       message="the job's gate")
    pid = sched._proc.pid
    if ending == "sigkill":
        os.kill(pid, signal.SIGKILL)
    os.waitid(os.P_PID, pid, os.WEXITED | os.WNOWAIT)  # it has ended and released the lock; not reaped yet
    with retrain_lock(data):  # another retrain takes the lock in that window, and notes its own phases
        note_phase(data, "training")
        assert read_lock_info(data)["pid"] == os.getpid()
    assert sched.wait_idle(timeout=30)
    rec = sched.history[0]
    assert rec.status is RetrainStatus.promoted and rec.version == version, rec
    assert promoted == [version] and finished == [rec]
    assert not list((data / "logs").glob("*.notes")), "the job's notes are the scheduler's to read once"


def test_a_job_that_never_took_the_lock_is_credited_with_nothing(data):
    """Its notes file was never written; the lock file's notes are another holder's."""
    theirs = ModelRegistry(data).champion()
    with retrain_lock(data):
        note_phase(data, "registered", version=theirs)
        sched = RetrainScheduler(ScheduleConfig(), data, lambda: 0, command=lambda d, extra: [
            sys.executable, "-c", "import sys; sys.exit('cannot start')"])
        sched.request()
        sched.tick()
        assert sched.wait_idle(timeout=30)
    rec = sched.history[0]
    assert (rec.status, rec.version) == (RetrainStatus.failed, ""), rec
