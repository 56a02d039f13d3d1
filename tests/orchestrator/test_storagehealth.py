"""orchestrator.storagehealth: a write outage said once, a failing read warned at most once a period."""

from __future__ import annotations

import logging

import pytest

from orchestrator.protocol import ErrorCode, ProtocolError
from orchestrator.storagehealth import StorageHealth
from storage.errors import CatalogError, CatalogUnavailableError, QueueUnavailableError


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


def test_a_read_that_keeps_raising_shows_its_traceback_once_then_a_line_a_period(caplog) -> None:
    """A planner with a bug raises on every batch, for weeks: one traceback, not one per batch."""
    clock, log = Clock(), logging.getLogger("test.storagehealth")
    health = StorageHealth(log, warn_every_s=60.0, clock=clock)

    def broken() -> int:
        raise ValueError("a bug")

    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        for _ in range(5):
            assert health.read("what the planner plans with", broken) is None
            clock.now += 20
        assert health.read("what the planner plans with", lambda: 3) == 3
    lines = [(r.levelname, r.getMessage(), r.exc_info is not None) for r in caplog.records]
    assert lines == [
        ("ERROR", "reading what the planner plans with failed (its traceback once; while it goes on failing, a line "
                  "at most every 60 s)", True),
        ("WARNING", "cannot read what the planner plans with: ValueError: a bug (2 more failure(s) since the last "
                    "warning); nothing was changed and leases run as usual (said at most every 60 s while it fails)",
         False),
        ("INFO", "reading what the planner plans with works again", False)], lines


def test_a_write_outage_is_said_once_and_timed(caplog) -> None:
    clock = Clock()
    health = StorageHealth(logging.getLogger("test.storagehealth"), clock=clock)
    assert health.writes_work() is None  # no outage
    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        health.write_failed(QueueUnavailableError("database or disk is full"))
        clock.now += 5
        health.write_failed(QueueUnavailableError("database or disk is full"))
    assert health.down_since == 100.0 and caplog.text.count("storage unavailable") == 1
    clock.now += 5
    assert health.writes_work() == 10.0 and health.down_since is None


def test_writing_notes_an_outage_whatever_wraps_it_and_raises_on(caplog) -> None:
    """Around every write of the service: one refused for a reason that passes is an outage, also when a
    caller's own error was raised from it (an admin op's wire refusal); any other error is not. Nothing is
    swallowed, and a write that works ends nothing (the reaper does, after extending the leases)."""
    health = StorageHealth(logging.getLogger("test.storagehealth"))
    with pytest.raises(KeyError), health.writing():
        raise KeyError("a bug, or a refusal of the request itself")
    with pytest.raises(CatalogError), health.writing():
        raise CatalogError("episode e1 is already indexed with other bytes")
    assert health.down_since is None
    with pytest.raises(ProtocolError) as info, health.writing():
        try:
            raise QueueUnavailableError("database is locked")
        except QueueUnavailableError as exc:
            raise ProtocolError(ErrorCode.UNAVAILABLE, str(exc)) from exc
    assert info.value.code == ErrorCode.UNAVAILABLE and health.down_since is not None
    with health.writing():
        pass
    assert health.down_since is not None
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="test.storagehealth"), pytest.raises(CatalogUnavailableError), \
            health.writing():
        raise CatalogUnavailableError("cannot store episode e2: No space left on device")
    assert "storage unavailable" not in caplog.text  # the same outage: said once


def test_an_outage_that_ends_at_every_reap_is_said_once_a_period(caplog) -> None:
    """The episodes' disk is full, the catalog's is not: each upload's write fails, the reaper's next write
    works. Said (and its end) once per ``warn_every_s``, not twice per upload; an outage that begins
    within the period and lasts is said once the period has passed."""
    clock = Clock()
    health = StorageHealth(logging.getLogger("test.storagehealth"), warn_every_s=60.0, clock=clock)
    exc = CatalogUnavailableError("cannot store episode e1: No space left on device")
    ended = []
    with caplog.at_level(logging.INFO, logger="test.storagehealth"):
        for _ in range(11):  # an upload every 6 s, a reap 1 s after each
            health.write_failed(exc)
            clock.now += 1
            ended.append(health.writes_work())
            clock.now += 5
        said = [r.getMessage() for r in caplog.records]
        caplog.clear()
        health.write_failed(exc)  # at 166: one that lasts
        for _ in range(2):
            clock.now += 30
            health.write_failed(exc)  # e.g. the reaper's own write, failing too
        lasting = [r.getMessage() for r in caplog.records]
    assert ended == [1.0] + [None] * 9 + [1.0]
    assert len(said) == 2 and said[0].startswith("storage unavailable: cannot store episode e1: No space left on "
                                                 "device; leases will not expire"), said
    assert said[1].startswith("storage unavailable: cannot store episode e1: No space left on device (9 shorter "
                              "outage(s) since the last said); leases"), said
    assert len(lasting) == 1 and "shorter" not in lasting[0], lasting  # at 226, 66 s after the last said
    assert health.down_since == 166.0 and health.writes_work() == 60.0
