"""A draining worker as a real subprocess: run's drain request (SIGUSR1) never escalates, an operator's second
signal still does, and a live service that will not store the upload does not hold the worker for ever."""

from __future__ import annotations

import signal
import threading

import pytest

from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError, QueueUnavailableError
from storage.requests import RequestStatus
from tests.conftest import in_hand, wait_for
from tests.orchestrator import conftest as orchestrator_fixtures
from tests.orchestrator.test_service import new_request

make_service = orchestrator_fixtures.make_service  # its in-process service, for these tests too


def send(w, sig: int, taken: str) -> None:
    """Signal ``w`` and wait until it has taken the signal (its log says ``taken`` once more): two signals sent at
    once may count as one."""
    before = w.log().count(taken)
    w.signal(sig)
    wait_for(lambda: w.log().count(taken) > before, message=f"{signal.Signals(sig).name} is taken ({taken!r})")


def test_the_drain_signal_twice_is_still_a_drain(make_service, spawn_worker, data_dir) -> None:
    """What `activecollect run` sends its workers: drain; nothing more when draining already."""
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=30))  # 3 s of paced collection
    w = spawn_worker("U", "--realtime", "1")
    in_hand(w, request.id)
    send(w, signal.SIGUSR1, "draining:")
    send(w, signal.SIGUSR1, "draining already")
    assert w.wait(30) == 0, w.log()
    done = service.queue.get(request.id)
    assert (done.status, done.attempts) == (RequestStatus.DONE, 0), w.log()
    assert Catalog(data_dir).count() == 1 and "INFO released " not in w.log()


def test_after_the_drain_signal_an_operators_second_stop_signal_still_gives_the_request_back(make_service,
                                                                                              spawn_worker) -> None:
    """The drain request does not count as a stop signal: the operator's first SIGTERM drains (as it would have
    anyway), the second drops the episode and gives the request back; the worker exits 1 saying so."""
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=100))  # 10 s of paced collection
    w = spawn_worker("O", "--realtime", "1")
    in_hand(w, request.id)
    send(w, signal.SIGUSR1, "draining:")
    send(w, signal.SIGTERM, "draining already")
    send(w, signal.SIGTERM, "stopping now")
    assert w.wait(30) == 1, w.log()
    back = service.queue.get(request.id)
    assert (back.status, back.attempts, back.last_error) == (RequestStatus.QUEUED, 0, None), w.log()
    assert f"released {request.id}" in w.log() and f"dropped the episode of {request.id}" in w.log()


@pytest.mark.parametrize("renewals", ["acknowledged", "refused"])
def test_a_draining_worker_whose_uploads_a_live_service_refuses_gives_up_and_exits_1(make_service, spawn_worker,
                                                                                     data_dir, renewals) -> None:
    """The service answers every upload `unavailable`, and renews the lease all along (its episode disk is full,
    its database's is not) or refuses renewals too (one full disk): the draining worker does not retry until
    killed. Within a lease term it says what it gave up, gives the request back (no attempt spent: the request
    did nothing wrong) and exits 1 (a live service would not store collected work: the operator must know)."""
    lease_s = 2.0
    service = make_service(lease_s=lease_s)
    request, _ = service.queue.enqueue(new_request(steps=30))  # 3 s of paced collection: renewed meanwhile
    refused: list[int] = []

    def full_disk(*args, **kw):
        refused.append(1)
        raise CatalogUnavailableError("episodes: No space left on device")

    service.catalog.ingest_bytes = full_disk
    if renewals == "refused":
        def renew_on_a_full_disk(*args, **kw):
            raise QueueUnavailableError("database catalog.sqlite: database or disk is full")
        service.queue.renew = renew_on_a_full_disk
    w = spawn_worker("V", "--realtime", "1")
    in_hand(w, request.id)
    send(w, signal.SIGTERM, "draining:")
    wait_for(lambda: not w.alive(), timeout=3 * lease_s + 15, message="the draining worker to give up")
    assert w.wait() == 1, w.log()
    assert refused, w.log()
    log = w.log()
    assert f"giving up the episode of {request.id}" in log and "unavailable" in log, log
    back = service.queue.get(request.id)
    assert (back.status, back.attempts, back.last_error) == (RequestStatus.QUEUED, 0, None), log
    assert f"released {request.id}" in log
    assert Catalog(data_dir).count() == 0


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGTERM], ids=["drain", "stop"])
def test_a_lease_granted_after_the_drain_began_is_given_back_unstarted(make_service, spawn_worker, data_dir,
                                                                       sig) -> None:
    """The drain signal comes while the worker's lease query is in flight: the request it is then granted is not
    the one in hand, so it is released (queued again, no attempt spent) instead of collected. (The old worker
    collected and uploaded it: an episode long at a real robot's pace held up ``activecollect run``'s stop.)"""
    service = make_service()
    request, _ = service.queue.enqueue(new_request())
    real, entered, go = service.queue.lease, threading.Event(), threading.Event()

    def held_lease(*args, **kw):
        entered.set()
        go.wait(30)
        return real(*args, **kw)

    service.queue.lease = held_lease
    w = spawn_worker("N")
    try:
        assert entered.wait(30), w.log()
        send(w, sig, "draining:")
    finally:
        go.set()
    assert w.wait(30) == 0, w.log()
    back = service.queue.get(request.id)
    assert (back.status, back.attempts, back.last_error) == (RequestStatus.QUEUED, 0, None), w.log()
    assert f"released {request.id}" in w.log() and Catalog(data_dir).count() == 0
    # "leased" is logged once a request is in hand, which this one never was (`in_hand` waits on that line)
    assert "granted after the drain began" in w.log() and f" leased {request.id} token " not in w.log(), w.log()


def test_a_worker_drained_while_no_service_answers_says_so_not_no_work(spawn_worker) -> None:
    """--once, and nobody answers its lease query yet: the drain ends the wait, and the log does not claim the
    service had no work (it never answered)."""
    w = spawn_worker("Q", "--once", "--timeout", "1")
    wait_for(lambda: "lease: no reply" in w.log(), timeout=60, message="the worker to wait for a service")
    send(w, signal.SIGTERM, "draining:")
    assert w.wait(30) == 0, w.log()
    assert "no work" not in w.log(), w.log()


def test_a_paced_episode_whose_lease_is_lost_is_dropped_without_waiting_out_its_pace(make_service, spawn_worker,
                                                                                       data_dir) -> None:
    """--realtime 1000 makes a 30-step episode last 50 minutes; the operator cancels the request meanwhile: the
    next renewal finds the lease lost and the worker drops the episode then (the old worker waited the whole
    pace out first)."""
    service = make_service(lease_s=1.5)
    request, _ = service.queue.enqueue(new_request(steps=30))
    w = spawn_worker("P", "--realtime", "1000")
    in_hand(w, request.id)
    service.queue.cancel(request.id)
    wait_for(lambda: "dropping the episode of" in w.log(), timeout=60, message="the episode dropped")
    assert f"lease of {request.id} lost" in w.log()
    assert service.queue.get(request.id).status == RequestStatus.CANCELLED and Catalog(data_dir).count() == 0
    w.signal(signal.SIGTERM)
    assert w.wait(30) == 0, w.log()


def test_a_draining_worker_goes_on_uploading_while_the_service_takes_its_parts(make_service, spawn_worker,
                                                                               data_dir) -> None:
    """A slow uplink, not a service that will not store: each part is taken, but the whole upload takes longer than
    a lease term. The draining worker used to give up one term after its first upload call (each part's wait cut
    to 0.5 s, the next slower part ended it) and drop an episode the service was storing."""
    lease_s, per_part_s = 2.0, 0.6
    service = make_service(lease_s=lease_s)
    request, _ = service.queue.enqueue(new_request(steps=10))  # 1 s of paced collection: the stop comes in it
    handler = service._uploads
    part, parts = handler._part, []

    def slow_link(payload, header):  # (each part's reply comes per_part_s after it was sent, as over ~2 kB/s)
        parts.append(len(payload))
        threading.Event().wait(per_part_s)
        return part(payload, header)

    handler._part = slow_link
    w = spawn_worker("S", "--realtime", "1", "--upload-part-kb", "1")
    in_hand(w, request.id)
    send(w, signal.SIGTERM, "draining:")
    assert w.wait(60) == 0, w.log()
    assert len(parts) * per_part_s > 1.5 * lease_s, parts  # (the upload did outlast the drain's first term)
    assert service.queue.get(request.id).status == RequestStatus.DONE and Catalog(data_dir).count() == 1, w.log()
