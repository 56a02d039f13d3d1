"""The lease renewer on its own: a renewal nobody answers must not cost the lease."""

from __future__ import annotations

import threading
import time
import types

import zenoh

from orchestrator import transport
from orchestrator.messages import LeaseGrant
from orchestrator.protocol import ErrorCode, ProtocolError
from tests.conftest import wait_for
import workers.lease
from workers.lease import Renewer

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}


class _Clock:
    """A monotonic clock that moves only when the renewer waits (on its stop event) or a call takes time."""

    def __init__(self) -> None:
        self.now = 0.0
        self.stops: list[threading.Event] = []
        """The stop events made since: the renewer's."""

    def monotonic(self) -> float:
        return self.now


def _on_the_tests_clock(monkeypatch) -> _Clock:
    """The renewer's module on a clock of the test's (no wall-clock figure): waiting on its stop event moves it."""
    clock = _Clock()

    class Stop(threading.Event):
        def __init__(self) -> None:
            super().__init__()
            clock.stops.append(self)

        def wait(self, timeout: float | None = None) -> bool:
            if not self.is_set() and timeout is not None:
                clock.now += timeout
            return self.is_set()

    monkeypatch.setattr(workers.lease, "time", types.SimpleNamespace(monotonic=clock.monotonic))
    monkeypatch.setattr(workers.lease, "threading", types.SimpleNamespace(Event=Stop, Thread=threading.Thread))
    return clock


def test_a_lost_renewal_waits_one_interval_and_the_next_comes_on_schedule(monkeypatch):
    """On a clock of the test's: the renewal whose reply is lost waits its whole timeout, one interval, and the
    next goes out when it was due, not an interval after the loss."""
    clock = _on_the_tests_clock(monkeypatch)
    grant = LeaseGrant(request_id="r1", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.6, lease_s=0.6)
    calls: list[tuple[float, float]] = []  # (when, the timeout it was given), on the test's clock

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append((clock.now, timeout))
        if len(calls) == 4:
            clock.stops[0].set()  # (the renewer's thread may get here before its constructor has returned)
        if len(calls) == 1:  # the first renewal's reply is lost: the query waits its whole timeout
            clock.now += timeout
            raise transport.TransportError("no reply")
        return {}

    renewer = Renewer(call, "ns/orch/renew", grant, "w1")
    wait_for(lambda: len(calls) >= 4, timeout=10, message="renewals after the lost one")
    interval = grant.lease_s / 3
    assert [round(when / interval, 6) for when, _ in calls] == [1, 2, 3, 4], calls
    assert all(t == interval for _, t in calls)  # one try never waits longer than the interval
    assert renewer.lost is None


def test_the_lease_lasts_lease_s_past_the_last_renewal_the_service_acknowledged():
    """What a draining worker's upload may wait for: acknowledged renewals extend it, unanswered ones do not."""
    grant = LeaseGrant(request_id="r2", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.6, lease_s=0.6)
    answered = threading.Event()
    answered.set()
    calls: list[float] = []

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append(time.monotonic())
        if not answered.is_set():
            raise transport.TransportError("no reply")
        return {}

    renewer = Renewer(call, "ns/orch/renew", grant, "w1")
    try:
        started = time.monotonic()
        wait_for(lambda: time.monotonic() - started > 2 * grant.lease_s and len(calls) >= 4, timeout=10,
                 message="renewals past the first lease")
        assert renewer.remaining() > 0  # (two leases later: extended)
        answered.clear()
        wait_for(lambda: renewer.remaining() <= 0, timeout=5, message="the lease to run out")
        assert renewer.lost is None and len(calls) >= 5  # renewals went on, unanswered
    finally:
        renewer.stop()


def test_a_run_of_failed_renewals_is_logged_once_per_interval_then_its_end(monkeypatch, caplog):
    """At a tiny lease a lost service made a WARNING per renewal (60 a second at --lease-s 0.05): a run of failures
    is one WARNING, then at most one per WARN_EVERY_S with the count, and an INFO when renewals are answered again."""
    answered = threading.Event()
    clock = _on_the_tests_clock(monkeypatch)
    grant = LeaseGrant(request_id="r3", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.06, lease_s=0.06)  # a renewal every 0.02 s of the test's clock
    calls: list[float] = []

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append(clock.now)
        if clock.now < 2.5 * workers.lease.WARN_EVERY_S:  # 12.5 s of the test's clock without an answer
            raise transport.TransportError("no reply")
        answered.set()
        return {}

    caplog.set_level("INFO", logger="workers.agent")
    renewer = Renewer(call, "ns/orch/renew", grant, "w1")
    try:
        wait_for(answered.is_set, timeout=30, message="the renewals answered again")
        wait_for(lambda: any("answered again" in r.getMessage() for r in caplog.records), timeout=10,
                 message="the log of the renewals answered again")
    finally:
        renewer.stop()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(calls) > 300  # (the renewer went on asking every interval)
    assert len(warnings) == 3, warnings  # at 0, WARN_EVERY_S and twice that: one per 5 s of failures
    assert warnings[0] == "renew r3: no reply"
    assert warnings[1].startswith("renew r3: no reply (") and "failed in a row)" in warnings[1]
    assert renewer.lost is None


def test_a_run_of_failed_renewals_ended_by_a_stop_says_its_count(monkeypatch, caplog):
    """The failures after a run's last WARNING were never counted in the log when the episode ended first (or the
    lease was lost): one said 1 failure, the next 300 went unsaid."""
    clock = _on_the_tests_clock(monkeypatch)
    grant = LeaseGrant(request_id="r4", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.06, lease_s=0.06)
    calls: list[float] = []
    fifth, stopped = threading.Event(), threading.Event()

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append(clock.now)
        if len(calls) == 5:  # in flight when the episode ends
            fifth.set()
            stopped.wait(30)
        raise transport.TransportError("no reply")

    caplog.set_level("INFO", logger="workers.agent")
    renewer = Renewer(call, "ns/orch/renew", grant, "w1")
    wait_for(fifth.is_set, timeout=30, message="five renewals sent")
    renewer.stop(wait=False)
    stopped.set()
    renewer.stop()
    said = [r.getMessage() for r in caplog.records]
    assert said == ["renew r4: no reply", "renew r4: 5 failed in a row when renewals stopped"]


def _failing_then(clock, failures: int, then):
    """A renewal call that fails ``failures`` times unanswered, then does ``then()``."""
    calls: list[float] = []

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append(clock.now)
        if len(calls) <= failures:
            raise transport.TransportError("no reply")
        return then()
    return call


def test_a_run_whose_failures_were_all_said_adds_no_line_when_renewals_stop(monkeypatch, caplog):
    """The count is said at the end only for failures after the run's last WARNING: one failure, warned, then the
    worker gives its request back and closes its session under the next renewal: the WARNING alone."""
    clock = _on_the_tests_clock(monkeypatch)
    grant = LeaseGrant(request_id="r5", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.06, lease_s=0.06)
    second, stopped = threading.Event(), threading.Event()

    def in_flight_when_the_episode_ends() -> dict:
        second.set()
        stopped.wait(30)
        raise zenoh.ZError("session closed")

    caplog.set_level("INFO", logger="workers.agent")
    renewer = Renewer(_failing_then(clock, 1, in_flight_when_the_episode_ends), "ns/orch/renew", grant, "w1")
    wait_for(second.is_set, timeout=30, message="the second renewal sent")
    renewer.stop(wait=False)
    stopped.set()
    renewer.stop()
    assert [r.getMessage() for r in caplog.records] == ["renew r5: no reply"]


def test_a_run_of_failed_renewals_ended_by_a_lost_lease_says_its_count_and_why(monkeypatch, caplog):
    clock = _on_the_tests_clock(monkeypatch)
    grant = LeaseGrant(request_id="r6", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.06, lease_s=0.06)

    def lost() -> dict:
        raise ProtocolError(ErrorCode.STALE_TOKEN, "expected the live lease")

    caplog.set_level("INFO", logger="workers.agent")
    renewer = Renewer(_failing_then(clock, 3, lost), "ns/orch/renew", grant, "w1")
    try:
        wait_for(lambda: renewer.lost is not None, timeout=30, message="the lease lost")
    finally:
        renewer.stop()
    said = [r.getMessage() for r in caplog.records]
    assert said[0] == "renew r6: no reply" and said[1].startswith("lease of r6 lost (stale_token)"), said
    assert said[2:] == ["renew r6: 3 failed in a row when renewals stopped (the lease was lost)"], said
