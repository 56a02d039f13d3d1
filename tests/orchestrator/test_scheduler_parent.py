"""A retrain job does not outlive the process that started it (its parent-death signal), and the scheduler's
thread, whose end sends that signal, outlives a job it was told to let finish."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading

from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from tests.conftest import REPO, alive, wait_for

#: A job that writes its pid to DATA/started, then runs until killed.
HANGS = "import os, pathlib, sys, time; pathlib.Path(sys.argv[1], 'started').write_text(str(os.getpid())); " \
        "time.sleep(600)"

#: A process that starts such a job from its scheduler's thread, then waits to be killed.
STARTS_A_JOB = f"""
import sys, threading
from pathlib import Path
from orchestrator.retrainjob import ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
data = Path(sys.argv[1])
sched = RetrainScheduler(ScheduleConfig(poll_s=0.05), data, lambda: 0,
                         command=lambda d, extra: [sys.executable, "-c", {HANGS!r}, str(d)])
sched.start()
sched.request()
threading.Event().wait()
"""


def test_a_job_dies_with_the_process_that_started_it(tmp_path):
    """`serve` or `run` killed outright (SIGKILL, the OOM killer): its retrain job is not left training."""
    parent = subprocess.Popen([sys.executable, "-c", STARTS_A_JOB, str(tmp_path)], cwd=REPO,
                              env=dict(os.environ, PYTHONPATH=str(REPO)))
    job = 0
    try:
        job = int(wait_for(lambda: (tmp_path / "started").is_file() and (tmp_path / "started").read_text(),
                           timeout=30, message="the job to start"))
        parent.kill()
        parent.wait()
        wait_for(lambda: not alive(job), timeout=10, message="the job to die with its parent")
    finally:
        parent.kill()
        parent.wait()
        if job and alive(job):
            os.kill(job, signal.SIGKILL)


def test_stopping_without_killing_lets_the_job_finish(tmp_path):
    """The job's parent is the scheduler's thread: ``stop(kill_running=False)`` must not end that thread
    (and so SIGTERM the job) before the job is done."""
    verdict = {"version": "m000003-cd", "promoted": False, "reason": "worse"}
    code = f"import time; time.sleep(1); print({json.dumps(json.dumps(verdict))})"
    sched = RetrainScheduler(ScheduleConfig(poll_s=0.05), tmp_path, lambda: 0,
                             command=lambda d, extra: [sys.executable, "-c", code])
    sched.start()
    sched.request()
    wait_for(lambda: sched.running, timeout=10, message="the job to start")
    sched.stop(kill_running=False)
    rec = sched.history[0]
    assert (rec.status, rec.returncode, rec.version) == (RetrainStatus.rejected, 0, "m000003-cd"), rec


def test_a_stop_signal_while_the_job_is_waited_for_terminates_it(tmp_path):
    """``run``'s stop after an error waits for a running retrain: a Ctrl-C then (``until``) ends the wait, and the
    job, at once (the old stop waited for the whole job, up to the retrain timeout)."""
    code = "import time; time.sleep(600)"
    sched = RetrainScheduler(ScheduleConfig(poll_s=0.05), tmp_path, lambda: 0,
                             command=lambda d, extra: [sys.executable, "-c", code])
    sched.start()
    sched.request()
    wait_for(lambda: sched.running, timeout=10, message="the job to start")
    signalled = threading.Event()
    threading.Timer(0.5, signalled.set).start()
    sched.stop(kill_running=False, until=signalled)
    assert not sched.running and sched.history[-1].status is RetrainStatus.killed
