"""Scheduled retraining: when jobs start, one at a time, and what a failed or killed job leaves."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from orchestrator.retrainlock import EXIT_BUSY, RetrainBusyError, lock_held, note_phase, read_lock_info, retrain_lock
from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from storage.catalog import Catalog
from storage.models import ModelRegistry
from tests.conftest import wait_for
from tests.orchestrator.conftest import small_training_data
from uncertainty.config import MAX_EPOCHS




def script_command(code: str):
    """A retrain job that runs ``code`` in a fresh Python (a real child process)."""
    return lambda data_dir, extra: [sys.executable, "-c", code, str(data_dir)]


PROMOTES = "import json; print(json.dumps({'version': 'm000002-ab', 'promoted': True, 'reason': 'better', " \
           "'metrics': {'h1_mse': 0.01}}))"
REJECTS = "import json; print(json.dumps({'version': 'm000003-cd', 'promoted': False, 'reason': 'worse'}))"
FAILS = "import sys; print('loading...'); sys.exit('CorruptCheckpointError: weights do not match')"
HANGS = "import pathlib, sys, time; pathlib.Path(sys.argv[1], 'started').touch(); time.sleep(600)"


class Counter:
    def __init__(self) -> None:
        self.n = 0

    def __call__(self) -> int:
        return self.n


def test_retrains_every_n_episodes_and_reports_a_promotion(tmp_path):
    episodes, promoted = Counter(), []
    sched = RetrainScheduler(ScheduleConfig(every_episodes=5), tmp_path, episodes, promoted.append,
                             command=script_command(PROMOTES))
    assert sched.tick() is None
    episodes.n = 4
    assert sched.tick() is None
    episodes.n = 5
    rec = sched.tick()
    assert rec is not None and rec.trigger == "episodes" and rec.episodes == 5
    assert sched.wait_idle(timeout=60)
    assert rec.status is RetrainStatus.promoted and rec.version == "m000002-ab" and rec.reason == "better"
    assert rec.metrics == {"h1_mse": 0.01} and promoted == ["m000002-ab"]
    assert sched.tick() is None  # the count restarts at the job's start
    json.dumps(rec.to_json())


def test_one_job_at_a_time(tmp_path, caplog):
    episodes = Counter()
    sched = RetrainScheduler(ScheduleConfig(every_episodes=1), tmp_path, episodes,
                             command=script_command(HANGS))
    episodes.n = 1
    first = sched.tick()
    assert first is not None
    episodes.n = 10
    assert sched.tick() is None and sched.running and len(sched.history) == 1
    with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
        sched.stop()
    assert first.status is RetrainStatus.killed and "stopped" in first.reason and not sched.running
    # no version yet: the log line says what happened, without a "-" for the missing version
    assert [r.getMessage() for r in caplog.records] == ["retrain killed: stopped with the scheduler"]


def test_a_promotion_is_logged_with_the_gate_s_words_once(tmp_path, caplog):
    gate_words = "import json; print(json.dumps({'version': 'm000002-ab', 'promoted': True, " \
                 "'reason': 'promoted: h1_mse 0.01 vs champion m000001-aa 0.02'}))"
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(gate_words))
    sched.request()
    sched.tick()
    with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
        assert sched.wait_idle(timeout=60)
    assert "retrain promoted m000002-ab: h1_mse 0.01 vs champion m000001-aa 0.02" in [
        r.getMessage() for r in caplog.records]


def test_a_jobs_warnings_reach_the_service_log(tmp_path, caplog):
    warns = "import json; print(json.dumps({'version': 'm000004-ef', 'promoted': True, 'reason': 'better', " \
            "'warnings': ['champion m000003 cannot be loaded (sha256): warm-started from m000002']}))"
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(warns))
    sched.request()
    sched.tick()
    with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
        assert sched.wait_idle(timeout=60)
    assert ("WARNING", "retrain m000004-ef: champion m000003 cannot be loaded (sha256): warm-started from m000002") in [
        (r.levelname, r.getMessage()) for r in caplog.records]


def test_a_failed_job_is_logged_with_its_reason_and_promotes_nothing(tmp_path):
    promoted = []
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), promoted.append, command=script_command(FAILS))
    sched.request()
    rec = sched.tick()
    assert sched.wait_idle(timeout=60)
    assert rec.status is RetrainStatus.failed and rec.returncode == 1
    assert "CorruptCheckpointError" in rec.reason and promoted == []
    assert Path(rec.log_path).read_text().strip().endswith("weights do not match")


def test_a_rejected_candidate_is_not_swapped_in(tmp_path):
    promoted = []
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), promoted.append, command=script_command(REJECTS))
    sched.request()
    rec = sched.tick()
    sched.wait_idle(timeout=60)
    assert rec.status is RetrainStatus.rejected and rec.reason == "worse" and promoted == []


def test_a_killed_job_is_recorded_as_killed(tmp_path):
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(HANGS))
    sched.request()
    rec = sched.tick()
    wait_for(lambda: (tmp_path / "started").exists(), message="the job to start")
    os.kill(sched._proc.pid, signal.SIGKILL)
    assert sched.wait_idle(timeout=30)
    assert rec.status is RetrainStatus.killed and rec.reason == "killed by SIGKILL"


def test_a_job_killed_by_a_signal_without_a_name_is_recorded(tmp_path):
    finished = []
    code = "import os; os.kill(os.getpid(), 35)"  # a real-time signal: signal.Signals(35) has no member
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), on_finished=finished.append,
                             command=script_command(code))
    sched.request()
    rec = sched.tick()
    assert sched.wait_idle(timeout=30)
    assert rec.status is RetrainStatus.killed and rec.reason == "killed by signal 35" and finished == [rec]


def test_a_job_that_cannot_start_is_a_failed_record_and_the_next_one_runs(tmp_path):
    finished = []
    commands = iter([lambda d, extra: [str(tmp_path / "no-such-program")], script_command(PROMOTES)])
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), on_finished=finished.append,
                             command=lambda d, extra: next(commands)(d, extra))
    sched.request()
    rec = sched.tick()
    assert rec.status is RetrainStatus.failed and "could not start the retrain job" in rec.reason
    assert finished == [rec] and not sched.running
    sched.request()
    assert sched.tick() is not None and sched.wait_idle(timeout=60)
    assert [r.status for r in sched.history] == [RetrainStatus.failed, RetrainStatus.promoted]


def test_the_scheduler_thread_outlives_a_failing_tick(tmp_path):
    calls = []

    def count() -> int:  # 0 at start-up, then briefly unreadable, then 10
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("database is locked")
        return 0 if len(calls) == 1 else 10

    sched = RetrainScheduler(ScheduleConfig(every_episodes=5, poll_s=0.05), tmp_path, count,
                             command=script_command(PROMOTES))
    sched.start()
    try:
        wait_for(lambda: len(sched.history) == 1, timeout=60, message="a job after the failed tick")
    finally:
        sched.stop()
    assert len(calls) >= 3


def test_a_job_past_its_timeout_is_killed(tmp_path):
    sched = RetrainScheduler(ScheduleConfig(timeout_s=0.5), tmp_path, Counter(), command=script_command(HANGS))
    sched.request()
    rec = sched.tick()
    wait_for(lambda: (tmp_path / "started").exists(), message="the job to start")
    wait_for(lambda: sched.tick() is None and not sched.running, timeout=30, message="the timeout")
    assert rec.status is RetrainStatus.timeout and "timed out" in rec.reason


def test_a_wall_clock_step_does_not_kill_a_healthy_job(tmp_path, monkeypatch):
    """An NTP step forward of an hour while a job runs: its timeout counts the time it ran, not the clock."""
    sched = RetrainScheduler(ScheduleConfig(timeout_s=60), tmp_path, Counter(), command=script_command(HANGS))
    sched.request()
    rec = sched.tick()
    try:
        wait_for(lambda: (tmp_path / "started").exists(), message="the job to start")
        wall = time.time
        with monkeypatch.context() as clock:
            clock.setattr(time, "time", lambda: wall() + 3600)  # the whole process's clock steps, as NTP's would
            assert sched.tick() is None
        assert sched.running and rec.status is RetrainStatus.running and rec.started <= wall()
    finally:
        sched.stop()
    assert rec.status is RetrainStatus.killed  # by the stop, not the timeout


def test_retrain_every_n_fires_at_each_multiple_of_n_also_across_restarts(tmp_path):
    # (n more than at the last start, tried in the thirtieth session, never fired for a service restarted more often
    # than it stored n episodes: a reviewer's reproduction, 300 episodes over 5 restarts, every 100, no retrain)
    episodes, fired = Counter(), []
    for life in range(5):  # five lives of the service, 60 episodes each
        sched = RetrainScheduler(ScheduleConfig(every_episodes=100), tmp_path, episodes,
                                 command=script_command(PROMOTES))
        for _ in range(60):
            episodes.n += 1
            if sched.tick() is not None:
                fired.append(episodes.n)
                assert sched.wait_idle(timeout=60)
        sched.stop()
    assert fired == [100, 200, 300]


def test_cron_schedule(tmp_path):
    sched = RetrainScheduler(ScheduleConfig(cron="*/5 * * * *"), tmp_path, Counter(),
                             command=script_command(PROMOTES))
    nxt = sched._next_cron
    assert nxt is not None and nxt > time.time() - 1
    assert sched.tick(now=nxt - 1) is None
    rec = sched.tick(now=nxt + 1)
    assert rec is not None and rec.trigger == "cron"
    sched.wait_idle(timeout=60)
    assert sched._next_cron > nxt
    with pytest.raises(ValueError, match="cron"):
        ScheduleConfig(cron="every five minutes")


def test_a_cron_schedule_set_back_by_hours_runs_at_its_next_time_not_hours_late(tmp_path, caplog):
    hourly = RetrainScheduler(ScheduleConfig(cron="0 * * * *"), tmp_path, Counter(), command=script_command(PROMOTES))
    nxt = hourly._next_cron
    assert hourly.tick(now=nxt - 1800) is None  # half an hour before the next
    assert hourly.tick(now=nxt - 1800 - 60) is None  # set back a minute: the same next, no retrain run twice
    assert hourly._next_cron == nxt
    with caplog.at_level(logging.WARNING, logger="orchestrator.scheduler"):
        assert hourly.tick(now=nxt - 1800 - 6 * 3600) is None  # set back 6 h: the next is in half an hour again
    assert hourly._next_cron == nxt - 6 * 3600 and "the wall clock went back 21540 s" in caplog.text
    rec = hourly.tick(now=nxt - 6 * 3600 + 1)
    assert rec is not None and rec.trigger == "cron"  # (it was 7 h away)
    hourly.wait_idle(timeout=60)
    assert hourly.tick(now=nxt - 6 * 3600 - 59) is None  # back a minute, before the time that ran: not again
    assert hourly._next_cron == nxt - 5 * 3600


def test_the_lock_admits_one_holder_across_processes(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time, pathlib\n"
        "from orchestrator.retrainlock import retrain_lock, note_phase\n"
        "with retrain_lock(pathlib.Path(sys.argv[1])):\n"
        "    note_phase(pathlib.Path(sys.argv[1]), 'training')\n"
        "    time.sleep(600)\n"), str(tmp_path)])
    try:
        wait_for(lambda: read_lock_info(tmp_path).get("phase") == "training", message="the holder")
        assert lock_held(tmp_path)
        with pytest.raises(RetrainBusyError, match=f"pid {holder.pid}, phase training"):
            with retrain_lock(tmp_path):
                pass
    finally:
        holder.kill()
        holder.wait()
    # the kernel dropped the dead holder's lock: no stale lock file to clean up
    assert not lock_held(tmp_path)
    with pytest.raises(RuntimeError):
        with retrain_lock(tmp_path):
            assert lock_held(tmp_path)
            note_phase(tmp_path, "training")
            raise RuntimeError("the job failed")
    assert read_lock_info(tmp_path)["phase"] == "failed" and not lock_held(tmp_path)
    assert EXIT_BUSY == 3


# -- the real retrain job: `activecollect retrain` ------------------------------------------------

TINY = ("--members", "2", "--widths", "4,4,4", "--batch-size", "8", "--device", "cpu", "--min-improvement", "0")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A data dir with an eval split, a few training episodes and a champion."""
    data = small_training_data(tmp_path_factory.mktemp("retrain"))
    first = retrain(data, "--epochs", "1")
    assert first.returncode == 0, first.stderr
    result = json.loads(first.stdout, parse_constant=_not_json)  # strict: what a cluster scheduler parses
    assert result["promoted"] is True
    return data


def _not_json(constant: str) -> None:
    raise ValueError(f"{constant} is not JSON")


def retrain(data: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "orchestrator", "retrain", "--data", str(data), "--json",
                           *TINY, *extra], capture_output=True, text=True, timeout=300)


def models(data: Path) -> list[str]:
    return [m.version for m in ModelRegistry(data).list()]


def champion(data: Path) -> str | None:
    return ModelRegistry(data).champion()


def test_retrain_json_is_strict_json_when_a_horizon_cannot_be_measured(tmp_path):
    """Episodes of 5 steps: h5 and h10 cannot be measured (NaN), and --json printed NaN, which a strict parser (a
    cluster scheduler's, jq) refuses; it is null, as every other --json writes it."""
    data = small_training_data(tmp_path / "data", steps=5)
    done = retrain(data, "--epochs", "1")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout, parse_constant=_not_json)
    assert result["metrics"]["h10_mse"] is None and result["metrics"]["h1_mse"] > 0


def test_a_retrain_killed_midway_leaves_the_champion(trained):
    before, versions = champion(trained), models(trained)
    promoted: list[str] = []
    sched = RetrainScheduler(ScheduleConfig(retrain_args=(*TINY, "--epochs", str(MAX_EPOCHS))), trained,
                             Counter(), promoted.append)
    sched.request()
    rec = sched.tick()
    wait_for(lambda: read_lock_info(trained).get("phase") == "training" and lock_held(trained),
             message="the retrain to start training")
    os.kill(sched._proc.pid, signal.SIGKILL)
    assert sched.wait_idle(timeout=60)
    assert rec.status is RetrainStatus.killed and rec.reason == "killed by SIGKILL"
    assert champion(trained) == before and models(trained) == versions and promoted == []
    assert not lock_held(trained)
    # and the next job runs normally
    done = retrain(trained, "--epochs", "1")
    assert done.returncode == 0, done.stderr
    assert len(models(trained)) == len(versions) + 1


@pytest.mark.timeout(600)
def test_two_retrains_at_once_train_once(trained):
    versions = models(trained)
    first = subprocess.Popen([sys.executable, "-m", "orchestrator", "retrain", "--data", str(trained), "--json",
                              *TINY, "--epochs", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: read_lock_info(trained).get("phase") == "training", message="the first retrain to train")
        second = retrain(trained, "--epochs", "1")
        assert first.poll() is None, "the first retrain ended before the second started; make it longer"
        assert second.returncode == EXIT_BUSY
        assert f"another retrain holds {trained / 'retrain.lock'} (pid {first.pid}, phase training)" in second.stderr
        out, err = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 0, err
    assert len(models(trained)) == len(versions) + 1 and json.loads(out)["version"] not in versions


def test_a_retrain_notes_the_model_it_registered_in_the_lock_file(trained, tmp_path):
    """What the scheduler reads when a job ends without reporting (see test_scheduler_after_gate.py)."""
    data = tmp_path / "copy"
    shutil.copytree(trained, data)
    done = retrain(data, "--epochs", "1")
    assert done.returncode == 0, done.stderr
    info = read_lock_info(data)
    assert (info["phase"], info["version"]) == ("done", json.loads(done.stdout)["version"]) and not lock_held(data)


def test_a_retrain_with_keep_models_prunes_after_its_gate(trained, tmp_path):
    from orchestrator.retrain import ABANDONED
    data = tmp_path / "copy"
    shutil.copytree(trained, data)
    registry = ModelRegistry(data)
    bad = registry.register(b"junk weights", {}, {"h1_mse": float("nan")}, "snap", "another-split")
    assert not registry.gate(bad).promoted
    # what a job killed between its register and its gate leaves: a candidate no job will gate
    left = registry.register(b"weights of a job that died", {}, {"h1_mse": 1.0}, "snap", "another-split")
    done = retrain(data, "--epochs", "1", "--keep-models", "1")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["abandoned"] == [left] and registry.get(left).reason == ABANDONED
    assert {bad, left} <= set(result["pruned"]) and not (data / "models" / bad).exists()
    assert not (data / "models" / left).exists()
    champ = ModelRegistry(data).champion()
    assert champ == result["champion"] and ModelRegistry(data).load_weights(champ)
    for rec in ModelRegistry(data).list():
        assert (rec.pruned_at is None) == (rec.version == champ), rec



def test_a_failing_prune_does_not_fail_the_retrain(trained, tmp_path, monkeypatch):
    from orchestrator.retrain import run_retrain
    from uncertainty.config import TrainConfig
    data = tmp_path / "copy"
    shutil.copytree(trained, data)

    def broken(self, keep, dry_run=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ModelRegistry, "prune", broken)
    cfg = TrainConfig(members=2, widths=(4, 4, 4), batch_size=8, epochs=1, device="cpu", min_rel_improvement=0,
                      progress=False)
    result = run_retrain(data, cfg, keep_models=1)
    assert result["pruned"] == [] and "No space left on device" in result["prune_error"]
    assert result["version"] in [m.version for m in ModelRegistry(data).list()]
    assert ModelRegistry(data).champion() == result["champion"]


def test_a_retrain_quarantines_a_lost_train_file_and_trains_on_the_rest(trained, tmp_path):
    from orchestrator.retrainjob import quarantined_note
    data = tmp_path / "copy"
    shutil.copytree(trained, data)
    catalog = Catalog(data)
    lost = catalog.list(split="train")[2]
    lost.path.unlink()  # a disk error, an operator's mistake: the file of an acknowledged episode is gone
    done = retrain(data, "--epochs", "1")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["quarantined"] == [lost.episode_id] and result["metrics"]["train_episodes"] == 5
    assert quarantined_note([lost.episode_id]) in done.stderr
    assert catalog.get(lost.episode_id).quarantined.startswith("found by a training job: ")
    assert ModelRegistry(data).get(result["version"]).snapshot_id == catalog.snapshot().snapshot_id
    again = retrain(data, "--epochs", "1")  # the next job trains on the same snapshot, nothing new to say
    assert again.returncode == 0 and json.loads(again.stdout)["quarantined"] == [] and again.stderr == ""


def test_a_retrain_in_text_says_what_it_pruned(trained, tmp_path):
    data = tmp_path / "copy"
    shutil.copytree(trained, data)
    done = subprocess.run([sys.executable, "-m", "orchestrator", "retrain", "--data", str(data), *TINY,
                           "--epochs", "1", "--keep-models", "1"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "pruned the files of " in done.stdout and done.stdout.splitlines()[0].startswith("m0")
    verdict = done.stdout.splitlines()[0].split(": ")
    assert verdict[1] in ("promoted", "not promoted") and verdict[2] != "promoted", done.stdout  # said once


def test_jobs_train_with_the_threads_the_schedule_gives_unless_their_own_args_say_otherwise(trained, tmp_path):
    assert RetrainScheduler(ScheduleConfig(retrain_args=TINY), tmp_path, Counter()).job_args() == TINY
    with pytest.raises(ValueError, match="threads must be >= 0, found -1"):
        ScheduleConfig(threads=-1)
    for name, own, threads in (("given", (), 3), ("own", ("--threads", "2"), 2)):
        data = tmp_path / name
        shutil.copytree(trained, data)
        sched = RetrainScheduler(ScheduleConfig(retrain_args=(*TINY, "--epochs", "1", *own), threads=3), data,
                                 Counter())
        assert sched.job_args()[:2] == ("--threads", "3")
        sched.request()
        rec = sched.tick()
        assert sched.wait_idle(timeout=240)
        assert rec.status in (RetrainStatus.promoted, RetrainStatus.rejected), rec.reason
        assert rec.metrics["train_threads"] == threads


def test_a_long_lived_scheduler_keeps_the_newest_records_and_job_logs(tmp_path, monkeypatch):
    """A service retraining for months: its history (the dashboard's table) and logs/ keep the newest jobs only."""
    import orchestrator.scheduler as scheduler
    monkeypatch.setattr(scheduler, "HISTORY_KEPT", 3)
    monkeypatch.setattr(scheduler, "LOGS_KEPT", 2)
    sched = RetrainScheduler(ScheduleConfig(), tmp_path, Counter(), command=script_command(REJECTS))
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "run-w0.log").write_text("a worker's log is not a retrain's")
    for name in ("retrain-20260101T000000-1.log", "retrain-20260101T000000-1.log.notes"):  # a killed service's job
        (tmp_path / "logs" / name).write_text("{}")
        os.utime(tmp_path / "logs" / name, (1.0, 1.0))
    started = []
    for _ in range(5):
        sched.request()
        started.append(sched.tick())
        assert started[-1] is not None and sched.wait_idle(timeout=60)
    assert sched.history == started[-3:] and all(r.status is RetrainStatus.rejected for r in started)
    kept = sorted(p.name for p in (tmp_path / "logs").iterdir())
    assert kept == sorted([Path(r.log_path).name for r in started[-2:]] + [Path(r.log_path).name + ".out"
                                                                            for r in started[-2:]] + ["run-w0.log"])

