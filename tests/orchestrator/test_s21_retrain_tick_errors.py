"""A catalog the scheduler cannot read for a while (a disk error, a damaged database) fails every tick, twice a
second by default: the failure is logged once, with its traceback, and its end once, not a traceback per tick."""

from __future__ import annotations

import logging

from orchestrator.retrainjob import ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from tests.conftest import wait_for


def test_a_tick_that_keeps_failing_is_logged_once_and_its_end_once(tmp_path, caplog):
    catalog = Catalog(tmp_path)
    calls = []

    def count() -> int:  # read at start-up, then unreadable for 20 ticks, then read again
        calls.append(1)
        if 2 <= len(calls) <= 21:
            raise CatalogUnavailableError(f"cannot read the catalog in {tmp_path}: disk I/O error")
        return catalog.count(split="train")

    sched = RetrainScheduler(ScheduleConfig(every_episodes=5, poll_s=0.01), tmp_path, count)
    with caplog.at_level(logging.INFO, logger="orchestrator.scheduler"):
        sched.start()
        try:
            wait_for(lambda: len(calls) >= 30, timeout=30, message="30 ticks")
        finally:
            sched.stop()
    ticks = [r for r in caplog.records if "tick" in r.getMessage()]
    said = [(r.levelno, r.getMessage()) for r in ticks]
    assert said == [
        (logging.ERROR, "retrain scheduler: tick failed; will try again (said once until a tick passes): "
                        f"CatalogUnavailableError: cannot read the catalog in {tmp_path}: disk I/O error"),
        (logging.INFO, "retrain scheduler: ticks pass again, after 20 that failed")], said
    assert ticks[0].exc_info is not None  # the traceback, once
    assert sched.history == []
