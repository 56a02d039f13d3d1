"""A retrain job that ends without reporting, after its gate decided: the record and ``on_promoted`` follow
what the registry says the job did, not only how its process ended."""

from __future__ import annotations

import json
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

#: A job that registers a model with the h1_mse of argv[2] and gates it under the lock, as ``activecollect
#: retrain`` does, writes the version to DATA/gated, then hangs (``hang``: a prune on a stalled disk) or fails
#: (``crash``).
GATES = """
import pathlib, sys, time
from orchestrator.retrain import training_job
data, h1, then = pathlib.Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
with training_job(data) as (catalog, registry, abandoned):
    version = registry.register(b'weights of this job', {}, {'h1_mse': h1, 'curve': [1, 2]}, 'snap', 'split')
    registry.gate(version)
    pathlib.Path(data, 'gated').write_text(version)
    if then == 'crash':
        raise RuntimeError('the disk went away while pruning')
    time.sleep(600)
"""


def job(h1_mse: float, then: str = "hang"):
    return lambda data_dir, extra: [sys.executable, "-c", GATES, str(data_dir), str(h1_mse), then]


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """A registry whose champion has h1_mse 0.02."""
    registry = ModelRegistry(tmp_path)
    assert registry.gate(registry.register(b"the champion's weights", {}, {"h1_mse": 0.02}, "snap", "split")).promoted
    return tmp_path


def start(data: Path, command, **cfg) -> tuple[RetrainScheduler, list[str], list]:
    promoted, finished = [], []
    sched = RetrainScheduler(ScheduleConfig(**cfg), data, lambda: 0, promoted.append, command=command,
                             on_finished=finished.append)
    sched.request()
    assert sched.tick() is not None
    return sched, promoted, finished


def gated(data: Path) -> str:
    return wait_for(lambda: (data / "gated").is_file() and (data / "gated").read_text(), timeout=60,
                    message="the job's gate")


@pytest.mark.parametrize("ending, words", [
    ("sigkill", "killed by SIGKILL"),
    ("stop", "stopped with the scheduler"),
    ("crash", "exit status 1: RuntimeError: the disk went away while pruning"),
])
def test_a_job_that_ends_without_reporting_after_its_gate_promoted_is_recorded_as_promoted(data, ending, words):
    sched, promoted, finished = start(data, job(0.01, "crash" if ending == "crash" else "hang"))
    version = gated(data)
    if ending == "sigkill":
        os.kill(sched._proc.pid, signal.SIGKILL)
    if ending == "stop":
        sched.stop()
    assert sched.wait_idle(timeout=30)
    rec = sched.history[0]
    assert ModelRegistry(data).champion() == version
    assert rec.status is RetrainStatus.promoted and rec.version == version, rec
    assert rec.reason.startswith("promoted: ") and rec.reason.endswith(
        f" (then the job ended without reporting it: {words})"), rec.reason
    assert rec.metrics == {"h1_mse": 0.01} and promoted == [version] and finished == [rec]
    json.dumps(rec.to_json())


def test_a_job_killed_after_its_gate_rejected_is_killed_and_names_its_model(data):
    sched, promoted, finished = start(data, job(0.05))
    version = gated(data)
    os.kill(sched._proc.pid, signal.SIGKILL)
    assert sched.wait_idle(timeout=30)
    rec = sched.history[0]
    assert rec.status is RetrainStatus.killed and rec.version == version, rec
    assert rec.reason.startswith(f"killed by SIGKILL, after its gate had rejected {version}: "), rec.reason
    assert promoted == [] and finished == [rec] and ModelRegistry(data).champion() != version


def test_a_promotion_by_another_holder_of_the_lock_is_not_the_killed_job_s(data):
    """A job told to wait for the lock (``retrain --wait``) is killed while another retrain, which holds it,
    promotes: the champion changed during the job, but not by it."""
    other = start(data, job(0.01))[0]  # another job, e.g. `activecollect retrain` from cron
    try:
        theirs = gated(data)
        waits = ("import pathlib, sys\nfrom orchestrator.retrainlock import retrain_lock\n"
                 "pathlib.Path(sys.argv[1], 'waiting').touch()\n"
                 "with retrain_lock(pathlib.Path(sys.argv[1]), wait=True):\n    pass\n")
        sched, promoted, finished = start(data, lambda d, extra: [sys.executable, "-c", waits, str(d)])
        wait_for(lambda: (data / "waiting").exists(), timeout=30, message="the job to wait for the lock")
        os.kill(sched._proc.pid, signal.SIGKILL)
        assert sched.wait_idle(timeout=30)
    finally:
        other.stop()
    rec = sched.history[0]
    assert ModelRegistry(data).champion() == theirs
    assert (rec.status, rec.version, rec.reason) == (RetrainStatus.killed, "", "killed by SIGKILL") and promoted == []


def test_a_job_that_had_reported_when_the_scheduler_stopped_is_recorded_by_its_report(tmp_path):
    """The job printed its verdict and exited, and ``stop`` came before the scheduler reaped it."""
    verdict = {"version": "m000002-ab", "promoted": True, "reason": "promoted: better", "metrics": {"h1_mse": 0.01}}
    sched, promoted, finished = start(tmp_path, lambda d, extra: [
        sys.executable, "-c", f"print({json.dumps(json.dumps(verdict))})"])
    os.waitid(os.P_PID, sched._proc.pid, os.WEXITED | os.WNOWAIT)  # exited, not reaped
    sched.stop()
    rec = sched.history[0]
    assert (rec.status, rec.version, rec.reason) == (RetrainStatus.promoted, "m000002-ab", "promoted: better")
    assert promoted == ["m000002-ab"] and finished == [rec]


def test_the_lock_file_keeps_the_version_its_holder_registered_until_the_next_holder(tmp_path):
    with pytest.raises(RuntimeError):
        with retrain_lock(tmp_path):
            note_phase(tmp_path, "training")
            assert "version" not in read_lock_info(tmp_path)
            note_phase(tmp_path, "registered", version="m000002-ab")
            note_phase(tmp_path, "done")
            assert read_lock_info(tmp_path)["version"] == "m000002-ab"
            raise RuntimeError("the job failed after its gate")
    info = read_lock_info(tmp_path)
    assert (info["phase"], info["version"], info["pid"]) == ("failed", "m000002-ab", os.getpid())
    with retrain_lock(tmp_path):  # the same process, a new job (bench loop): nothing registered yet
        assert "version" not in read_lock_info(tmp_path)


#: A job that dies before taking the lock (a bad flag: exit 2), whose pid the lock file names with an earlier
#: holder's notes: what the kernel's reuse of a pid (a restarted container) leaves. argv[2]: the earlier version.
STALE_PID = """
import json, os, pathlib, sys, time
pathlib.Path(sys.argv[1], 'retrain.lock').write_text(json.dumps(
    {'pid': os.getpid(), 'phase': 'done', 'time': time.time() - 86400, 'version': sys.argv[2]}))
sys.exit(2)
"""


def test_an_earlier_holders_notes_under_a_pid_used_again_are_not_the_dead_jobs(data):
    """The lock file outlives its holder; a later job that gets the same pid and dies before locking must not be
    credited with the earlier job's promotion (recorded as promoted, announced again)."""
    earlier = ModelRegistry(data).champion()
    sched, promoted, finished = start(data, lambda d, extra: [sys.executable, "-c", STALE_PID, str(d), earlier])
    assert sched.wait_idle(timeout=30)
    rec = sched.history[0]
    assert read_lock_info(data)["version"] == earlier  # the stale notes, under this job's pid
    assert rec.status is RetrainStatus.failed and rec.version == "" and promoted == [], rec


def test_a_listener_that_raises_neither_ends_the_stop_nor_keeps_on_finished_from_its_news(data, caplog):
    """``stop`` finishing a job whose gate promoted calls ``on_promoted``; one that raises (a registry read that
    failed) is logged, ``on_finished`` still hears of the job, and the stop ends as stops do (a service's
    Ctrl-C then goes on to stop the service)."""
    finished = []

    def promoted(version: str) -> None:
        raise OSError(5, "Input/output error")

    sched = RetrainScheduler(ScheduleConfig(), data, lambda: 0, promoted, command=job(0.01),
                             on_finished=finished.append)
    sched.request()
    assert sched.tick() is not None
    version = gated(data)
    sched.stop()
    assert [(r.status, r.version) for r in finished] == [(RetrainStatus.promoted, version)]
    assert "retrain: promoted failed" in caplog.text and "Input/output error" in caplog.text
