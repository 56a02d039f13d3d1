"""The service's clocks: leases judged by a steady clock that steps of the wall clock do not move, carried over a
restart, and kept when the service itself did not run (frozen, or its reaper waiting for the writer turn). In-process
services (``make_service``, with fake wall and elapsed clocks) and a real Zenoh client over loopback."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from orchestrator import messages
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, upload


@pytest.mark.parametrize("step_s", [3600.0, -3600.0], ids=["forward", "back"])
def test_a_step_of_the_wall_clock_moves_no_lease(make_service, client, keys, step_s) -> None:
    # NTP steps the clock (or a VM or a laptop wakes up): forward, every live lease expired at once and its worker
    # dropped the episode it was collecting; back, a vanished worker's lease stayed for the length of the step
    wall = [time.time()]
    service = make_service(lease_s=30.0 if step_s > 0 else 0.5, wall_clock=lambda: wall[0])
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    real, reaps = service.metrics.read_stores, []

    def counted(*args, **kw):  # the reaper reads the gauges after each expiry pass
        reaps.append(1)
        return real(*args, **kw)

    service.metrics.read_stores = counted
    wall[0] += step_s
    if step_s < 0:
        wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
                 message="the lease to expire one term after it was granted, the step back notwithstanding")
        return
    seen = len(reaps)
    wait_for(lambda: len(reaps) >= seen + 2, message="two reaper passes after the step")
    assert service.queue.get(request.id).status == RequestStatus.LEASED
    renew = messages.RenewRequest(request_id=grant.request_id, token=grant.token, worker_id="w1").to_json()
    assert call(client, keys.renew, renew)["expires_at"] >= grant.expires_at  # (a refusal raises)
    upload(client, keys, grant, episode_bytes(grant))
    done = service.queue.get(request.id)
    assert (done.status, done.attempts) == (RequestStatus.DONE, 0)


def test_a_service_that_did_not_run_for_longer_than_a_lease_expires_none(make_service, client, keys,
                                                                         caplog) -> None:
    """SIGSTOP, a paused container or VM: the monotonic clock goes on while nothing of the service runs, so no
    worker can renew; on waking, its reaper expired every live lease at once (each worker dropped its episode and
    was charged an attempt). Here the service's elapsed clock jumps a minute between two reaper passes."""
    jumped = [0.0]
    service = make_service(lease_s=30.0, elapsed=lambda: time.monotonic() + jumped[0])
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    caplog.set_level(logging.WARNING, logger="orchestrator.service")
    jumped[0] = 60.0
    wait_for(lambda: any("the service did not run for 60 s" in r.getMessage() for r in caplog.records),
             message="the reaper to see the service stood still")
    assert service.queue.get(request.id).status == RequestStatus.LEASED
    upload(client, keys, grant, episode_bytes(grant))
    done = service.queue.get(request.id)
    assert (done.status, done.attempts) == (RequestStatus.DONE, 0)


class _WatchedTurn:
    """The service's writer turn, counting who waits for it."""

    def __init__(self) -> None:
        self._lock, self.waiting = threading.Lock(), 0

    def __enter__(self) -> None:
        self.waiting += 1  # (a count to wait on, not exact under races: the test holds the turn meanwhile)
        self._lock.acquire()
        self.waiting -= 1

    def __exit__(self, *exc: object) -> None:
        self._lock.release()


def test_a_stall_while_the_reaper_waits_for_the_writer_turn_expires_no_lease(make_service, client, keys,
                                                                            caplog) -> None:
    """The reaper read its clock before it waited for the turn (behind an ingest, say): frozen while it waited,
    it woke with the old reading, judged itself on time and expired every lease."""
    jumped = [0.0]
    service = make_service(lease_s=30.0, elapsed=lambda: time.monotonic() + jumped[0])
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    caplog.set_level(logging.WARNING, logger="orchestrator.service")
    turn = service._writes = _WatchedTurn()
    with turn:
        wait_for(lambda: turn.waiting > 0, message="the reaper to wait for the writer turn")
        jumped[0] = 60.0  # frozen for a minute while it waited
    wait_for(lambda: any("the service did not run for 60 s" in r.getMessage() for r in caplog.records),
             message="the reaper to see the service stood still")
    assert service.queue.get(request.id).status == RequestStatus.LEASED
    upload(client, keys, grant, episode_bytes(grant))


def test_a_lease_reckoned_a_day_ahead_by_the_last_service_gets_one_term_at_a_restart(make_service, client,
                                                                                      keys) -> None:
    """The last service's steady clock ran a day ahead of the wall clock (which NTP then stepped back): its
    leases' expiries are a day out. At a restart each gets one term from now, as any live lease does -- kept as
    they were, a worker that died with that service held its request for a day (a reviewer's reproduction)."""
    service = make_service(lease_s=30.0, wall_clock=lambda: time.time() + 86400)
    request, _ = service.queue.enqueue(new_request())
    lease(client, keys)
    assert service.queue.get(request.id).lease_expires > time.time() + 86000
    service.stop()
    service = make_service(lease_s=0.5)  # the wall clock right again; the worker is gone for good
    wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
             message="the vanished worker's lease to run out one term after the restart")
