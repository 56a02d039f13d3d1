"""The worker agent as a real subprocess against an in-process service: renew, drain, give back, late service."""

from __future__ import annotations

import signal
import threading

import pytest

from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from storage.requests import RequestStatus
from tests.conftest import disposition, ignoring_sigint, in_hand, wait_for
from tests.orchestrator.test_service import new_request
from workers.agent import WorkerConfig, WorkerError


def test_worker_config_is_validated() -> None:
    with pytest.raises(WorkerError, match="worker_id"):
        WorkerConfig(worker_id="a/b")
    with pytest.raises(WorkerError, match="shapes"):
        WorkerConfig(shapes=("hexagon",))
    with pytest.raises(WorkerError, match="image_size"):
        WorkerConfig(image_size=2)
    for size in (8, 12, 20, 1032):  # its size becomes the catalog's when it uploads the first episode
        with pytest.raises(WorkerError, match=rf"image_size: expected a multiple of 8 from 16 to 1024 pixels "
                                              rf"\(what a model trains on\), found {size}"):
            WorkerConfig(image_size=size)
    assert WorkerConfig(image_size=16).image_size == 16
    assert WorkerConfig().worker_id  # <host>-<pid>


def test_renewals_keep_a_lease_alive_past_lease_s(make_service, spawn_worker) -> None:
    service = make_service(lease_s=0.6)
    request, _ = service.queue.enqueue(new_request(steps=20))  # 2 s of paced collection > 3 leases
    w = spawn_worker("R", "--realtime", "1", "--once")
    assert w.wait(60) == 0, w.log()
    done = service.queue.get(request.id)
    assert (done.status, done.attempts, done.token) == (RequestStatus.DONE, 0, 1)


@pytest.mark.parametrize("error", [
    CatalogUnavailableError("database catalog.sqlite: database or disk is full"),  # what a full disk gives now
    OSError(28, "No space left on device"),  # anything unforeseen: `internal`
], ids=["unavailable", "internal"])
def test_an_upload_the_service_could_not_store_is_retried_not_failed(make_service, spawn_worker, data_dir,
                                                                     error) -> None:
    """``unavailable`` (a full disk, a busy database) and ``internal`` are transient: the same bytes again,
    no attempt spent."""
    service = make_service()
    request, _ = service.queue.enqueue(new_request())
    real, refused = service.catalog.ingest_bytes, []

    def full_disk_once(*args, **kw):
        if not refused:
            refused.append(1)
            raise error
        return real(*args, **kw)

    service.catalog.ingest_bytes = full_disk_once
    w = spawn_worker("U", "--once")
    assert w.wait(60) == 0, w.log()
    done = service.queue.get(request.id)
    assert refused and (done.status, done.attempts) == (RequestStatus.DONE, 0), w.log()
    assert Catalog(data_dir).count() == 1


def test_sigterm_drains_the_current_request(make_service, spawn_worker, data_dir) -> None:
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=20))
    other, _ = service.queue.enqueue(new_request(steps=5))
    w = spawn_worker("D", "--realtime", "1")
    in_hand(w, request.id)
    w.signal(signal.SIGTERM)
    assert w.wait(30) == 0, w.log()
    assert service.queue.get(request.id).status == RequestStatus.DONE  # finished, not dropped
    assert service.queue.get(other.id).status == RequestStatus.QUEUED  # and took nothing new
    assert Catalog(data_dir).count() == 1


def test_a_worker_started_ignoring_sigint_keeps_ignoring_it(make_service, spawn_worker) -> None:
    """As `activecollect run` started in a script's background does (the shell starts it so): its workers
    must not stop on a SIGINT their run ignores."""
    make_service()
    with ignoring_sigint():
        ignoring = spawn_worker("I")
    plain = spawn_worker("P")
    for w in (ignoring, plain):  # SIGTERM caught: the worker's handlers are in place
        wait_for(lambda: disposition(w.pid, signal.SIGTERM) == "caught", timeout=30, message=f"{w.name} handlers")
    assert disposition(ignoring.pid, signal.SIGINT) == "ignored"
    assert disposition(plain.pid, signal.SIGINT) == "caught"


def test_second_sigterm_gives_the_request_back(make_service, spawn_worker) -> None:
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=100))  # 10 s of paced collection
    w = spawn_worker("G", "--realtime", "1")
    in_hand(w, request.id)
    w.signal(signal.SIGTERM)
    wait_for(lambda: "draining" in w.log(), message="the first signal is taken")  # two at once may count as one
    w.signal(signal.SIGTERM)
    assert w.wait(30) == 1, w.log()  # (exit 1: the second signal dropped an episode, never acknowledged)
    back = service.queue.get(request.id)
    # Released, not failed: no attempt counted and no error (a lost worker would have cost an attempt too).
    assert (back.status, back.attempts, back.token, back.last_error) == (RequestStatus.QUEUED, 0, 1, None)
    assert f"released {request.id}" in w.log()


def test_worker_started_before_the_service_waits_and_then_works(make_service, spawn_worker) -> None:
    w = spawn_worker("E", "--max-episodes", "1")
    wait_for(lambda: "worker E up" in w.log(), timeout=30, message="the worker is up, no service yet")
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=5))
    assert w.wait(60) == 0, w.log()
    assert service.queue.get(request.id).status == RequestStatus.DONE


def test_a_worker_records_at_the_frame_size_the_service_holds(make_service, spawn_worker, data_dir) -> None:
    """A worker started with another --size still records what the catalog holds (its grant says so)."""
    service = make_service()
    service.queue.enqueue(new_request())
    first = spawn_worker("F", "--once")  # 16 px: the catalog's first episode fixes its size
    assert first.wait(60) == 0, first.log()
    request, _ = service.queue.enqueue(new_request())
    other = spawn_worker("S", "--size", "24", "--once")
    assert other.wait(60) == 0, other.log()
    done = service.queue.get(request.id)
    assert (done.status, done.attempts) == (RequestStatus.DONE, 0), other.log()
    assert Catalog(data_dir).load(done.episode_id).frames.shape[1:3] == (16, 16)


def test_a_second_sigterm_walks_away_from_an_upload_in_flight(make_service, spawn_worker) -> None:
    """The service takes the upload and never answers it (the worker's query waits its whole 10 s timeout):
    a second SIGTERM must not wait that out, nor a renewal in flight: the request is given back at once."""
    service = make_service()
    request, _ = service.queue.enqueue(new_request())
    entered, hang = threading.Event(), threading.Event()

    def never_answered(*args, **kw):
        entered.set()
        hang.wait(60)
        raise CatalogUnavailableError("the test's hung upload ends (nothing stored)")

    service.catalog.ingest_bytes = never_answered
    w = spawn_worker("H")
    try:
        assert entered.wait(30), w.log()
        w.signal(signal.SIGTERM)
        wait_for(lambda: "draining" in w.log(), message="the first signal is taken")
        w.signal(signal.SIGTERM)
        # (exit 1: an episode dropped; the old worker waited out the upload's 10 s, said so, then the release's)
        assert w.wait(60) == 1, w.log()
        assert "upload: " not in w.log(), w.log()
    finally:
        hang.set()
    back = service.queue.get(request.id)
    assert (back.status, back.attempts, back.last_error) == (RequestStatus.QUEUED, 0, None), w.log()
    assert f"released {request.id}" in w.log()


def test_a_draining_worker_gives_up_an_upload_nobody_answers_when_its_lease_runs_out(make_service, spawn_worker,
                                                                                    data_dir) -> None:
    """SIGTERM, then the service goes away before the episode is uploaded: the worker does not retry for ever
    (a supervisor would SIGKILL it); it drops the episode nobody acknowledged once its lease has run out."""
    lease_s = 2.0
    service = make_service(lease_s=lease_s)
    request, _ = service.queue.enqueue(new_request(steps=30))  # 3 s of paced collection
    w = spawn_worker("L", "--realtime", "1")
    in_hand(w, request.id)
    w.signal(signal.SIGTERM)
    wait_for(lambda: "draining" in w.log(), message="the first signal is taken")
    service.stop()
    assert w.wait(30) == 0, w.log()  # (the old worker retried until killed)
    assert f"dropping the episode of {request.id}: draining" in w.log()
    assert Catalog(data_dir).count() == 0


def test_a_worker_whose_lease_another_process_with_its_id_completed_says_the_id_is_shared(make_service,
                                                                                        spawn_worker) -> None:
    """Two processes given one --id: the second is answered the lease the first holds, and both collect it. The
    one that uploads second is refused (the service logs the error); the one that is still collecting when the
    other's upload completes the request learns it from its next renewal, and says why (it used to drop its
    episode with a bare 'lease lost', and the shared id went unnoticed)."""
    service = make_service(lease_s=0.6)
    request, _ = service.queue.enqueue(new_request(steps=40))
    slow = spawn_worker("X", "--realtime", "1", "--once")  # 4 s of paced collection
    in_hand(slow, request.id)
    fast = spawn_worker("X", "--once")  # the same id: handed the same lease, uploads at once
    assert fast.wait(60) == 0, fast.log()
    assert slow.wait(60) == 0, slow.log()
    done = service.queue.get(request.id)
    assert (done.status, done.attempts, done.token) == (RequestStatus.DONE, 0, 1)
    assert "two workers share the id X and collect every request twice; give each its own --id" in slow.log()
    assert "ERROR" not in fast.log()
