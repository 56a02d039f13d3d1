"""``activecollect run``'s worker logs stay bounded: each run appends to ``DATA/logs/run-w<i>.log``, and one found
over ``WORKER_LOG_BYTES`` at start is rotated to ``run-w<i>.log.1`` first (at most two files per worker index)."""

from __future__ import annotations

import sys

import orchestrator.loop
from orchestrator.loop import WORKER_LOG_BYTES
from tests.conftest import run_cli


def test_a_large_worker_log_is_rotated_when_a_run_starts_and_a_small_one_is_appended_to(tmp_path, monkeypatch,
                                                                                          capsys):
    """The logs grew by every run's output for as long as the data directory was used (months of runs)."""
    monkeypatch.setattr(orchestrator.loop, "worker_command",  # workers that say who they are, then exit at once
                        lambda endpoint, namespace, wid, size: [sys.executable, "-c",
                                                               f"print('worker {wid} ran'); raise SystemExit(3)"])
    data = tmp_path / "data"
    logs = data / "logs"
    logs.mkdir(parents=True)
    with open(logs / "run-w0.log", "wb") as f:  # months of runs (sparse: its size is what counts)
        f.write(b"an earlier run's output\n")
        f.truncate(WORKER_LOG_BYTES + 1)
    (logs / "run-w0.log.1").write_text("the oldest runs' output\n")
    (logs / "run-w1.log").write_text("an earlier run's output\n")

    rc, out, err = run_cli(capsys, "run", "--data", str(data), "--budget", "4", "--round", "2", "--workers", "2",
                           "--steps", "3", "--image-size", "16", "--eval-episodes", "1", "--dashboard-port", "-1",
                           "--no-progress")

    assert rc == 1 and err.strip().splitlines()[-1] == (
        f"activecollect run: all 2 workers exited (codes [3, 3]); see {logs}"), err[-2000:]
    assert sorted(p.name for p in logs.iterdir()) == ["run-w0.log", "run-w0.log.1", "run-w1.log"]
    rotated = logs / "run-w0.log.1"  # the large one, replacing the older .1
    assert rotated.stat().st_size == WORKER_LOG_BYTES + 1
    with open(rotated, "rb") as f:
        assert f.readline() == b"an earlier run's output\n"
    assert (logs / "run-w0.log").read_text() == "worker run-w0 ran\n"
    assert (logs / "run-w1.log").read_text() == "an earlier run's output\nworker run-w1 ran\n"
