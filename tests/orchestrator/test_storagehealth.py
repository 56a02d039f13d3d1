"""orchestrator.storagehealth: a write outage said once, a failing read warned at most once a period."""

from __future__ import annotations

import logging

from orchestrator.storagehealth import StorageHealth
from storage.errors import CatalogUnavailableError, QueueUnavailableError


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_failing_read_is_warned_once_a_period_with_the_failures_in_between(caplog) -> None:
    clock, log = Clock(), logging.getLogger("test.storagehealth")
    health = StorageHealth(log, warn_every_s=60.0, clock=clock)
    exc = CatalogUnavailableError("disk I/O error")
    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        for _ in range(5):
            health.read_failed("the gauges", exc)
            clock.now += 10
        health.read_failed("the planner's scorer", exc)  # another read: its own warning
        clock.now += 20
        health.read_failed("the gauges", exc)  # 70 s after the first warning
        health.read_worked("the gauges")
        health.read_worked("the gauges")  # said once
    lines = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in lines] == ["WARNING", "WARNING", "WARNING", "INFO"], lines
    assert lines[0][1].startswith("cannot read the gauges: disk I/O error; nothing was changed")
    assert lines[1][1].startswith("cannot read the planner's scorer: disk I/O error;")
    assert lines[2][1].startswith("cannot read the gauges: disk I/O error (4 more failure(s) since the last "
                                  "warning)"), lines[2]
    assert lines[3][1] == "reading the gauges works again"
    assert health.down_since is None  # reads never make the storage "down"


def test_a_read_returns_its_value_or_none(caplog) -> None:
    health = StorageHealth(logging.getLogger("test.storagehealth"))
    assert health.read("x", lambda: 7) == 7

    def broken() -> int:
        raise ValueError("a bug")

    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        assert health.read("x", broken) is None
    assert "reading x failed" in caplog.text and "ValueError: a bug" in caplog.text


def test_a_write_outage_is_said_once_and_timed(caplog) -> None:
    clock = Clock()
    health = StorageHealth(logging.getLogger("test.storagehealth"), clock=clock)
    assert health.writes_work() == 0.0
    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        health.write_failed(QueueUnavailableError("database or disk is full"))
        clock.now += 5
        health.write_failed(QueueUnavailableError("database or disk is full"))
    assert health.down_since == 100.0 and caplog.text.count("storage unavailable") == 1
    clock.now += 5
    assert health.writes_work() == 10.0 and health.down_since is None
