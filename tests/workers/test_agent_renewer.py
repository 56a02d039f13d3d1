"""The lease renewer on its own: a renewal nobody answers must not cost the lease."""

from __future__ import annotations

import threading
import time

from orchestrator import transport
from orchestrator.messages import LeaseGrant
from tests.conftest import wait_for
from workers.lease import Renewer

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}


def test_a_lost_renewal_waits_one_interval_and_the_next_comes_on_schedule():
    grant = LeaseGrant(request_id="r1", task="push", shape="box", start_state=START, policy="push",
                       policy_params={}, action_prefix=[], steps=5, model_version="", token=1,
                       expires_at=time.time() + 0.6, lease_s=0.6)
    calls: list[tuple[float, float]] = []  # (when, the timeout it was given)
    lost = threading.Event()

    def call(key: str, msg: bytes, timeout: float) -> dict:
        calls.append((time.monotonic(), timeout))
        if len(calls) == 1:  # the first renewal's reply is lost: the query waits its whole timeout
            lost.wait(timeout)
            raise transport.TransportError("no reply")
        return {}

    renewer = Renewer(call, "ns/orch/renew", grant, "w1")
    try:
        wait_for(lambda: len(calls) >= 3, timeout=10, message="renewals after the lost one")
    finally:
        renewer.stop()
    interval = grant.lease_s / 3
    assert all(t <= interval for _, t in calls)  # one try never waits longer than the interval
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
