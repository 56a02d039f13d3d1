"""Retrain schedules that cannot be kept are refused when the schedule is made, in one line: a cron expression
that never fires, and the 6- and 7-field forms croniter also reads (seconds, years) where a cron user means
minutes and hours."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from orchestrator.retrainjob import ScheduleConfig
from orchestrator.scheduler import RetrainScheduler


@pytest.mark.parametrize("cron, words", [
    ("0 0 31 2 *", "cron '0 0 31 2 *' never fires"),  # 31 February
    ("0 0 30 2 *", "cron '0 0 30 2 *' never fires"),
    ("0 * * * * *", "cron must be a cron expression of 5 fields"),  # croniter: every second of minute 0
    ("* * * * * *", "cron must be a cron expression of 5 fields"),  # croniter: every second
    ("0 0 1 1 * 0 2030", "cron must be a cron expression of 5 fields"),  # once, in 2030, then never again
])
def test_a_schedule_that_cannot_be_kept_is_refused(tmp_path, cron, words):
    with pytest.raises(ValueError, match=f"^{re.escape(words)}"):
        ScheduleConfig(cron=cron)


@pytest.mark.parametrize("cron", ["*/10 * * * *", "0 3 * * 1-5", "@hourly", "@daily", "0 0 29 2 *"])
def test_five_fields_and_the_at_names_are_schedules(tmp_path, cron):
    sched = RetrainScheduler(ScheduleConfig(cron=cron), tmp_path, lambda: 0)
    assert sched._next_cron is not None


def test_serve_refuses_a_cron_that_never_fires_in_one_line(tmp_path):
    done = subprocess.run([sys.executable, "-m", "orchestrator", "serve", "--data", str(tmp_path), "--init",
                           "--retrain-cron", "0 0 31 2 *", "--dashboard-port", "-1"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "never fires" in lines[0], done.stderr
    assert not (tmp_path / "catalog.sqlite").exists()  # refused before anything started
