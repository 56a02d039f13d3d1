"""Stopping a worker (a real subprocess) at the awkward moments: while it starts, in the middle of a long
collection, and while it reports a failure to a service that does not answer."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import pytest

from storage.catalog import Catalog
from storage.requests import RequestStatus
from tests.conftest import in_hand, wait_for
from tests.orchestrator import conftest as orchestrator_fixtures
from tests.orchestrator.test_service import new_request
from tests.workers.test_agent_drain import send

make_service = orchestrator_fixtures.make_service  # its in-process service, for these tests too


def importing_numpy(pid: int) -> bool:
    """The process has numpy's core extension mapped: ``python -m workers.agent`` is in its imports, which go on
    for a while after it (the simulator, MCAP, Zenoh) before the worker's own signal handlers are installed."""
    return "_multiarray_umath" in Path(f"/proc/{pid}/maps").read_text()


def hung(real, entered: threading.Event, go: threading.Event):
    """``real``, a queue method, answering only once the test is over: the worker's query to it waits its whole
    timeout meanwhile."""
    def method(*args, **kw):
        entered.set()
        go.wait(60)
        return real(*args, **kw)
    return method


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_a_signal_while_the_worker_starts_ends_it_cleanly_in_one_line(spawn_worker, sig) -> None:
    """`run` (SIGUSR1) or an operator (SIGINT, SIGTERM) stops a worker that is still importing: it holds no lease,
    so it exits 0 saying so in one line. (The old worker died of SIGUSR1 and SIGTERM, and printed a
    KeyboardInterrupt traceback for SIGINT.)"""
    w = spawn_worker("S")  # nobody listens on its endpoint: it would wait for a service once up
    wait_for(lambda: importing_numpy(w.pid), timeout=30, message="the worker to import numpy", interval=0.002)
    w.signal(sig)
    assert w.wait(30) == 0, w.log()
    lines = w.log().strip().splitlines()
    assert len(lines) == 1 and f"worker S: {sig.name} while starting" in lines[0], lines


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGTERM], ids=lambda s: s.name)
def test_a_signal_while_activecollect_worker_starts_ends_it_cleanly_in_one_line(spawn, endpoint, namespace,
                                                                                 sig) -> None:
    """The same through the `activecollect` command (`python -m orchestrator`, whose console script is the same
    entry point), whose imports (torch among them) take longer: the old one died of the signal (exit -10, -15)."""
    w = spawn("worker-A", "worker", "--connect", endpoint, "--namespace", namespace, "--id", "A", "--size", "16")
    wait_for(lambda: importing_numpy(w.pid), timeout=30, message="the worker to import numpy", interval=0.002)
    w.signal(sig)
    assert w.wait(60) == 0, w.log()
    lines = w.log().strip().splitlines()
    assert len(lines) == 1 and f"worker A: {sig.name} while starting" in lines[0], lines


@pytest.mark.parametrize("service_answers", [True, False], ids=["release answered", "release unanswered"])
def test_a_second_stop_signal_drops_the_episode_in_collection_at_once(make_service, spawn_worker, data_dir,
                                                                      service_answers) -> None:
    """600 steps at 1024 px take seconds to collect (tens at 1000 steps): the operator's second Ctrl-C must not
    wait for that. The worker drops the episode mid-collection, gives the request back (queued again, no attempt
    spent) or, when the release is not answered, leaves the lease to run out, and exits 1 in a line naming the
    request. (The old worker collected and encoded the whole episode first, then exited 0.)"""
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=600))
    entered, go = threading.Event(), threading.Event()
    if not service_answers:
        service.queue.release = hung(service.queue.release, entered, go)
    w = spawn_worker("C", "--size", "1024")
    try:
        in_hand(w, request.id)
        send(w, signal.SIGTERM, "draining:")
        send(w, signal.SIGTERM, "stopping now")
        assert w.wait(10) == 1, w.log()  # (the release waits 2 s at most; the old worker collected on, exit 0)
    finally:
        go.set()
    log = w.log()
    assert f"dropped the episode of {request.id} (collecting: stopped after " in log, log
    assert "INFO uploaded" not in log and Catalog(data_dir).count() == 0
    if service_answers:
        back = service.queue.get(request.id)
        assert (back.status, back.attempts, back.last_error) == (RequestStatus.QUEUED, 0, None), log
    else:
        assert entered.is_set() and f"release of {request.id} not answered" in log, log


def test_a_stopping_worker_does_not_retry_a_failure_report_nobody_answers(make_service, spawn_worker) -> None:
    """A poison request fails; the service does not answer the report (gone, or hung): the worker retries it
    while working, but once drained it stops retrying and exits within a few seconds, saying what it could not
    report. (The old worker went on for all 8 tries, each waiting its whole --timeout: ~100 s at the default
    10 s, past the 30 s `run` gives it.)"""
    service = make_service()
    entered, go = threading.Event(), threading.Event()
    service.queue.fail = hung(service.queue.fail, entered, go)
    request, _ = service.queue.enqueue(new_request(policy_params={"fail": True}))
    w = spawn_worker("F", "--timeout", "2")
    try:
        wait_for(lambda: "fail: no reply" in w.log(), timeout=30, message="the worker to retry its report")
        send(w, signal.SIGUSR1, "draining:")
        assert w.wait(10) == 0, w.log()  # the report in flight waits out its --timeout at most (old: ~100 s)
    finally:
        go.set()
    log = w.log()
    assert entered.is_set() and f"stopping: could not report the failure of {request.id} (collection failed" in log
    assert log.count("fail: no reply") <= 2, log  # the try the drain found in flight, and no other



def test_a_drained_worker_does_not_wait_long_for_a_renewal_nobody_answers(make_service, spawn_worker) -> None:
    """The service stops answering renewals (its renew queryable closed) but stores the upload that comes a second
    after one went out (30 s lease: one every 10 s, each waiting up to 10 s for its reply): the drained worker exits
    within a few seconds of the upload. (The old worker waited for that renewal to time out first.)"""
    service = make_service(lease_s=30.0)
    request, _ = service.queue.enqueue(new_request(steps=110))  # 11 s of paced collection: one renewal, at 10 s
    w = spawn_worker("R", "--realtime", "1")
    in_hand(w, request.id)
    next(s for s in service._servers if s.key_expr == service.keys.renew).close()
    send(w, signal.SIGUSR1, "draining:")
    wait_for(lambda: f"uploaded {request.id}" in w.log(), timeout=40, message="the upload")
    assert w.wait(60) == 0, w.log()
    # (the old worker waited for the renewal in flight to time out, ~9 s more, and logged it; the new one exits
    # without waiting it out)
    assert f"renew {request.id}: " not in w.log(), w.log()
    assert service.queue.get(request.id).status == RequestStatus.DONE


def test_a_stop_signal_while_the_worker_exits_does_not_kill_it(make_service, spawn_worker) -> None:
    """systemd's SIGTERM to the group can reach a worker that has just finished (``activecollect run`` drained it, or
    --max-episodes was reached): it holds nothing any more, so it still exits 0. (The old worker's handlers were
    put back to the default by Python's own shutdown: a SIGTERM in those last milliseconds killed it, exit -15,
    once in a CI run of `tests/test_run.py`'s group-stop test.)"""
    service = make_service()
    service.queue.enqueue(new_request(steps=5))
    w = spawn_worker("X", "--max-episodes", "1")
    wait_for(lambda: "done: 1 uploaded" in w.log(), timeout=60, message="the worker to finish its one episode",
             interval=0.002)
    sent = 0
    while w.alive():  # through the rest of its exit, finalisation included
        w.signal(signal.SIGTERM)
        sent += 1
        time.sleep(0.001)
    assert w.wait(30) == 0 and sent > 0, (sent, w.log())
    assert service.catalog.count(split="train") == 1
