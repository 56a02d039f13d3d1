"""A backup carries the retrain schedule of its source: a retrain owed when it was taken is run where it serves."""

from __future__ import annotations

import json
import logging

import numpy as np

from orchestrator.retrainjob import RetrainStatus, ScheduleConfig
from orchestrator.scheduler import COUNT_FILE, DUE_MARKER, RetrainScheduler
from tests.conftest import run_cli, wait_for
from tests.orchestrator.test_scheduler import HANGS, PROMOTES, Counter, script_command
from tests.storage.test_backup import _filled


def _job_registered(data, seed: int):
    """A filled data directory whose scheduled job (5 episodes) has registered its model, not yet gated: the
    model's version and the job's notes file."""
    from storage.models import ModelRegistry
    _filled(data, np.random.default_rng(seed))
    version = ModelRegistry(data).register(b"weights" * 10, {}, {"h1_mse": 0.01}, snapshot_id="s",
                                           eval_split_hash="h")
    notes = data / "logs" / "retrain-1.log.notes"
    notes.parent.mkdir(exist_ok=True)
    notes.write_text(json.dumps({"phase": "registered", "version": version}))
    (data / DUE_MARKER).write_text(json.dumps({"trigger": "episodes", "notes": str(notes)}))
    (data / COUNT_FILE).write_text("5")
    return version, notes


def test_a_multiple_reached_before_the_backup_and_not_yet_retrained_is_retrained_where_it_serves(tmp_path, capsys):
    data, dest = tmp_path / "data", tmp_path / "b1"
    _filled(data, np.random.default_rng(3))
    episodes = Counter()
    sched = RetrainScheduler(ScheduleConfig(every_episodes=10), data, episodes, command=script_command(PROMOTES))
    episodes.n = 10
    assert sched.tick() is not None and sched.wait_idle(timeout=60)
    sched.stop()
    episodes.n = 21  # 20 reached while no service ran (an offline ingest): owed at the next start here

    assert run_cli(capsys, "backup", "--data", str(data), str(dest))[0] == 0

    assert (dest / COUNT_FILE).read_text() == "10"
    copy = RetrainScheduler(ScheduleConfig(every_episodes=10), dest, episodes, command=script_command(PROMOTES))
    rec = copy.tick()
    assert rec is not None and rec.trigger == "episodes" and copy.wait_idle(timeout=60)
    copy.stop()


def test_a_job_running_when_the_backup_was_taken_runs_again_where_it_serves(tmp_path, capsys, caplog):
    """Its model is not in the backup's snapshot: the copy started with the job's count and ran nothing."""
    data, dest, again = tmp_path / "data", tmp_path / "b1", tmp_path / "b2"
    _filled(data, np.random.default_rng(4))
    episodes = Counter()
    sched = RetrainScheduler(ScheduleConfig(every_episodes=5), data, episodes, command=script_command(HANGS))
    episodes.n = 5
    assert sched.tick() is not None
    wait_for(lambda: (data / "started").exists(), message="the job to start")
    try:
        assert run_cli(capsys, "backup", "--data", str(data), str(dest))[0] == 0
    finally:
        sched.stop()
    assert run_cli(capsys, "backup", "--data", str(dest), str(again))[0] == 0  # a backup of the backup

    words = json.loads((dest / DUE_MARKER).read_text())["copied"]
    assert words == f"starting, when {data.resolve()} was backed up"
    assert json.loads((again / DUE_MARKER).read_text())["copied"] == words
    with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
        copy = RetrainScheduler(ScheduleConfig(every_episodes=5), dest, episodes, command=script_command(PROMOTES))
    assert words in caplog.text
    rec = copy.tick()
    assert rec is not None and rec.trigger == "episodes" and copy.wait_idle(timeout=60)
    assert rec.status is RetrainStatus.promoted and not (dest / DUE_MARKER).exists()
    copy.stop()


def test_a_job_past_its_gate_by_its_notes_is_not_run_again_from_the_backup(tmp_path, capsys):
    data, dest = tmp_path / "data", tmp_path / "b1"
    _filled(data, np.random.default_rng(5))
    notes = data / "logs" / "retrain-1.log.notes"
    notes.parent.mkdir()
    notes.write_text(json.dumps({"phase": "done", "version": "m000009-ff"}))
    (data / DUE_MARKER).write_text(json.dumps({"trigger": "episodes", "notes": str(notes)}))  # (its service killed)
    (data / COUNT_FILE).write_text("5")

    assert run_cli(capsys, "backup", "--data", str(data), str(dest))[0] == 0

    assert not (dest / DUE_MARKER).exists() and (dest / COUNT_FILE).read_text() == "5"
    episodes = Counter()
    episodes.n = 5
    assert RetrainScheduler(ScheduleConfig(every_episodes=5), dest, episodes,
                            command=script_command(PROMOTES)).tick() is None


def test_a_job_gated_between_the_snapshot_and_the_schedule_read_runs_again_from_the_backup(tmp_path, capsys):
    """A gate, its "done" note and the marker's removal that land between the snapshot and the schedule's read left
    the copy with the model a candidate, no marker and the job's count (a diff review's reproduction, and the
    marker's removal beside it: the marker is read before the snapshot now)."""
    from storage.backup import backup
    from storage.models import ModelRegistry, ModelStatus

    from orchestrator.scheduler import carry_schedule
    data, dest = tmp_path / "data", tmp_path / "b1"
    version, notes = _job_registered(data, 6)

    def carry(source):  # the job's gate, its last note and its marker's removal, between the snapshot and the copy
        write = carry_schedule(source)

        def after_the_snapshot(copy):
            ModelRegistry(source).gate(version)  # (no champion here: promoted)
            notes.write_text(json.dumps({"phase": "done", "version": version}))
            (source / DUE_MARKER).unlink()  # (the service's ``_finish``)
            write(copy)
        return after_the_snapshot

    backup(data, dest, carry=carry)

    assert ModelRegistry(dest).get(version).status is ModelStatus.CANDIDATE
    assert json.loads((dest / DUE_MARKER).read_text())["copied"].startswith("gated after the snapshot")
    episodes = Counter()
    episodes.n = 5
    assert RetrainScheduler(ScheduleConfig(every_episodes=5), dest, episodes,
                            command=script_command(PROMOTES))._retry == "episodes"


def test_a_hand_edited_marker_is_a_job_to_run_again_and_names_the_source_by_its_full_path(tmp_path, capsys,
                                                                                            monkeypatch):
    """A marker whose notes are not a path (``{"notes": 5}``) stopped the backup with a TypeError after its copy;
    a relative ``--data`` was named relative in the copy's words, which the copy's service reads elsewhere."""
    data, dest = tmp_path / "data", tmp_path / "b1"
    _filled(data, np.random.default_rng(7))
    (data / DUE_MARKER).write_text(json.dumps({"trigger": "episodes", "notes": 5}))
    monkeypatch.chdir(tmp_path)

    assert run_cli(capsys, "backup", "--data", "data", str(dest))[0] == 0

    assert json.loads((dest / DUE_MARKER).read_text())["copied"] == f"starting, when {data.resolve()} was backed up"


def test_a_job_registered_and_gated_after_the_snapshot_runs_again_from_the_backup(tmp_path, capsys):
    """The job was training at the snapshot: its model, registered and gated after it, is not in the copy, and its
    notes say "done" by the time they are read. The copy, with the job's count and no model of it, owes the job."""
    from storage.backup import backup
    from storage.models import ModelRegistry

    from orchestrator.scheduler import carry_schedule
    data, dest = tmp_path / "data", tmp_path / "b1"
    _filled(data, np.random.default_rng(8))
    notes = data / "logs" / "retrain-1.log.notes"
    notes.parent.mkdir(exist_ok=True)
    notes.write_text(json.dumps({"phase": "training"}))
    (data / DUE_MARKER).write_text(json.dumps({"trigger": "episodes", "notes": str(notes)}))
    (data / COUNT_FILE).write_text("5")
    registered = []

    def carry(source):
        write = carry_schedule(source)

        def after_the_snapshot(copy):  # the job registers, gates and notes "done" before its notes are read
            registry = ModelRegistry(source)
            version = registry.register(b"weights" * 10, {}, {"h1_mse": 0.01}, snapshot_id="s", eval_split_hash="h")
            registry.gate(version)
            notes.write_text(json.dumps({"phase": "done", "version": version}))
            registered.append(version)
            write(copy)
        return after_the_snapshot

    backup(data, dest, carry=carry)

    assert registered[0] not in [m.version for m in ModelRegistry(dest).list()]
    assert json.loads((dest / DUE_MARKER).read_text())["copied"].startswith("gated after the snapshot")
    episodes = Counter()
    episodes.n = 5
    assert RetrainScheduler(ScheduleConfig(every_episodes=5), dest, episodes,
                            command=script_command(PROMOTES))._retry == "episodes"


def test_the_schedule_is_read_before_the_snapshot_so_a_gate_just_before_the_read_is_in_the_copy(tmp_path, capsys):
    """``carry(source)`` is called before the snapshot: a gate (and the marker's removal) that lands just before the
    schedule is read is in the snapshot too. Read after the snapshot, the copy kept the model a candidate with
    nothing owed: the job lost where the copy serves."""
    from storage.backup import backup
    from storage.models import ModelRegistry, ModelStatus

    from orchestrator.scheduler import carry_schedule
    data, dest = tmp_path / "data", tmp_path / "b1"
    version, notes = _job_registered(data, 9)

    def carry(source):  # the job's gate, its last note and its marker's removal, then the schedule's read
        ModelRegistry(source).gate(version)
        notes.write_text(json.dumps({"phase": "done", "version": version}))
        (source / DUE_MARKER).unlink()
        return carry_schedule(source)

    backup(data, dest, carry=carry)

    gated = ModelRegistry(dest).get(version).status is not ModelStatus.CANDIDATE
    assert gated and not (dest / DUE_MARKER).exists()  # (a candidate with no marker would be a job lost)
