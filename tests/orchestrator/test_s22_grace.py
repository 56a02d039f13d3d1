"""A lost worker's grace (``ServiceConfig.lost_worker_grace_s``, ``serve --lost-worker-grace``): a worker whose
liveliness token goes keeps its leases that long. Back within it (a router restart, a link's blip), nothing is
released and its upload is stored; away past it, its leases go back to the queue as before; 0 releases at once."""

from __future__ import annotations

import json
import logging
import signal
import sys

import pytest

from orchestrator import transport
from orchestrator.liveliness import Presence
from orchestrator.protocol import EventKind
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig, ServiceError
from storage.catalog import Catalog
from storage.queue import RequestQueue
from storage.requests import RequestStatus
from tests.conftest import free_port, run_cli, wait_for
from tests.orchestrator.test_reliability import Ops
from tests.orchestrator.test_router import start_plain_router
from tests.orchestrator.test_secure import Proc
from tests.orchestrator.test_service import episode_bytes, lease, new_request, upload


@pytest.fixture
def heard(endpoint: str, keys):
    """``heard(kind)``: a session of its own (opened after the service, so connected at once), and the data of every
    ``kind`` event it hears from then on (the list fills as they come)."""
    sessions: list = []

    def listen(kind: EventKind):
        seen: list[dict] = []

        def on_event(sample) -> None:
            event = json.loads(sample.payload.to_bytes())
            if event["kind"] == kind.value:
                seen.append(event["data"])

        session = transport.open_session(connect=[endpoint])
        sessions.append((session, session.declare_subscriber(keys.events_all, on_event)))
        return session, seen

    yield listen
    for session, _ in sessions:
        session.close()


def present(service: Service, endpoint: str, keys, *worker_ids: str):
    """A worker's own session and the tokens of ``worker_ids`` it holds (a token dropped is undeclared), once the
    service sees them all."""
    session = transport.open_session(connect=[endpoint])
    tokens = [session.liveliness().declare_token(keys.worker(worker_id)) for worker_id in worker_ids]
    wait_for(lambda: set(worker_ids) <= set(service.workers()), message=f"the service to see {worker_ids}")
    return session, tokens


def messages_of(caplog, needle: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if needle in r.getMessage()]


def test_a_token_back_within_the_grace_keeps_the_lease_and_the_upload_is_stored(make_service, heard, endpoint,
                                                                                 keys, caplog) -> None:
    """The worker's session closes (its token goes) and a new one with the same id declares it again: the grace
    runs out with the worker back, nothing was released, and the episode of the first lease is stored."""
    service = make_service(lost_worker_grace_s=3.0)
    _, lost = heard(EventKind.WORKER_LOST)
    request, _ = service.queue.enqueue(new_request())
    first, _tokens = present(service, endpoint, keys, "w9")
    grant = lease(first, keys, worker="w9")
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        first.close()
        wait_for(lambda: "w9" not in service.workers(), message="the service to see the token go")
        again, _again = present(service, endpoint, keys, "w9")
        wait_for(lambda: service.presence.pending() == 0, timeout=10, message="the grace to run out")
        held = service.queue.get(request.id)
        assert (held.status, held.worker_id, held.token, held.attempts) == (RequestStatus.LEASED, "w9", 1, 0)
        wait_for(lambda: messages_of(caplog, "worker w9 back after"), message="the line that says it is back")
    assert messages_of(caplog, "back after")[0].endswith("s; its 1 lease(s) kept"), caplog.text
    assert not messages_of(caplog, "worker w9 lost") and lost == []
    stored = upload(again, keys, grant, episode_bytes(grant, worker="w9"), worker="w9")
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id) == (RequestStatus.DONE, stored["episode_id"])
    again.close()


@pytest.mark.parametrize("grace_s", [0.0, 1.0])
def test_a_token_away_past_the_grace_releases_the_lease_as_before(make_service, heard, endpoint, keys, caplog,
                                                                  grace_s) -> None:
    """Grace 0 is the behaviour from before (released at once); with a grace, released once it is over: the same
    WORKER_LOST event, log line and last error."""
    service = make_service(lost_worker_grace_s=grace_s)
    client, lost = heard(EventKind.WORKER_LOST)
    request, _ = service.queue.enqueue(new_request())
    worker, _tokens = present(service, endpoint, keys, "w9")
    lease(worker, keys, worker="w9")
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        worker.close()
        if grace_s:  # the token gone, its grace running: the lease is still held
            wait_for(lambda: service.presence.pending() == 1 or lost, message="the grace to start")
            assert service.queue.get(request.id).status == RequestStatus.LEASED and not lost
        wait_for(lambda: service.queue.get(request.id).status == RequestStatus.QUEUED, timeout=10,
                 message="the lost worker's lease to be released (lease_s is 30 s)")
        wait_for(lambda: lost, message="the WORKER_LOST event")
    assert lost == [{"worker_id": "w9", "released": [request.id]}]
    assert messages_of(caplog, "worker w9 lost") == ["worker w9 lost; 1 lease(s) released"]
    assert "worker w9 lost" in service.queue.get(request.id).last_error and service.queue.get(request.id).attempts == 1
    assert lease(client, keys, worker="w2").token == 2  # the old lease is fenced off


def test_a_worker_that_leaves_holding_no_lease_is_said_to_be_gone_not_lost(make_service, heard, endpoint, keys,
                                                                          caplog) -> None:
    # a worker that finished (--max-episodes) and exited was logged "lost; 0 lease(s) released", the line of a
    # real loss: an alert on it fired for every clean exit (an operator's review)
    service = make_service(lost_worker_grace_s=0.0)
    client, lost = heard(EventKind.WORKER_LOST)
    worker, _tokens = present(service, endpoint, keys, "w7")
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        worker.close()
        wait_for(lambda: lost, message="the WORKER_LOST event")
    assert lost == [{"worker_id": "w7", "released": []}]
    assert messages_of(caplog, "worker w7") == ["worker w7 gone; it held no lease"]


def test_a_fleet_lost_at_once_releases_only_the_leases_of_those_still_away(make_service, endpoint, keys,
                                                                           caplog) -> None:
    """Twelve tokens go together (one session: a router's restart looks like this); six come back within the grace.
    One heap holds all twelve graces: the six back keep their leases, said in one line each; the six others are
    released when the grace is over."""
    service = make_service(lost_worker_grace_s=3.0)
    ids = [f"w{i:02d}" for i in range(12)]
    for _ in ids:
        service.queue.enqueue(new_request())
    fleet, _tokens = present(service, endpoint, keys, *ids)
    requests = {w: lease(fleet, keys, worker=w).request_id for w in ids}
    back, away = ids[:6], ids[6:]
    with caplog.at_level(logging.INFO, logger="orchestrator.service"):
        fleet.close()
        wait_for(lambda: service.presence.pending() == 12, message="twelve graces running")
        returned, _back = present(service, endpoint, keys, *back)
        wait_for(lambda: all(service.queue.get(requests[w]).status == RequestStatus.QUEUED for w in away), timeout=10,
                 message="the leases of the six still away to be released")
        wait_for(lambda: service.presence.pending() == 0, message="every grace looked at")
    for w in back:
        held = service.queue.get(requests[w])
        assert (held.status, held.worker_id, held.attempts) == (RequestStatus.LEASED, w, 0)
        assert len(messages_of(caplog, f"worker {w} back after")) == 1
    assert sorted(m.split()[1] for m in messages_of(caplog, "lease(s) released")) == away
    assert all(m.endswith("its 1 lease(s) kept") for m in messages_of(caplog, "back after")), caplog.text
    returned.close()


def test_stop_does_not_wait_for_a_pending_grace(make_service, endpoint, keys, data_dir) -> None:
    service = make_service(lost_worker_grace_s=3600.0)
    request, _ = service.queue.enqueue(new_request())
    worker, _tokens = present(service, endpoint, keys, "w9")
    lease(worker, keys, worker="w9")
    worker.close()
    wait_for(lambda: service.presence.pending() == 1, message="the grace to start")
    service.stop()
    # (joined for up to 30 s: a thread still waiting on the grace would be alive after that)
    assert not [t.name for t in service._threads if t.is_alive()]
    with RequestQueue(Catalog(data_dir).db_path) as queue:  # left as it was: the next service carries it over
        assert queue.get(request.id).status == RequestStatus.LEASED


def test_a_worker_through_a_restarted_router_keeps_its_lease_and_its_episode_is_stored(tmp_path, caplog) -> None:
    """The real thing: a service and a worker process, both Zenoh clients of a router that is killed mid-episode
    and started again. Every token goes with it and comes back about a second later; within the grace the
    request stays the worker's (token 1, no attempt counted) and its upload is stored. (Before, the service
    queued the request again the moment the router went, and the worker's upload was refused as stale.)"""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_plain_router((endpoint,))
    routers, worker = [router], None
    service = Service(ServiceConfig(data_dir=tmp_path / "data", mode="client", connect=(endpoint,), lease_s=60.0,
                                    reap_interval_s=0.2, lost_worker_grace_s=30.0))
    try:
        service.start()
        request, _ = service.queue.enqueue(new_request(steps=60))
        worker = Proc([sys.executable, "-m", "workers.agent", "--mode", "client", "--connect", endpoint,
                       "--id", "wr", "--size", "16", "--realtime", "1", "--once"])
        wait_for(lambda: service.queue.get(request.id).status == RequestStatus.LEASED, 60, "the worker's lease")
        with caplog.at_level(logging.INFO, logger="orchestrator.service"):
            router.popen.send_signal(signal.SIGKILL)
            router.popen.wait(15)
            wait_for(lambda: "wr" not in service.workers(), 15, "the service to see the worker's token go")
            routers.append(start_plain_router((endpoint,)))
            wait_for(lambda: "wr" in service.workers(), 60, "the worker's token back through the new router")
            assert worker.popen.wait(90) == 0, worker.output()
            done = service.queue.get(request.id)
            assert (done.status, done.worker_id, done.token, done.attempts) == (RequestStatus.DONE, "wr", 1, 0), done
            wait_for(lambda: messages_of(caplog, "worker wr back after"), message="the line that says it is back")
        assert [e.episode_id for e in service.catalog.list()] == [done.episode_id]
        assert not messages_of(caplog, "worker wr lost"), caplog.text
    finally:
        if worker is not None:
            worker.stop()
        service.stop()
        for r in routers:
            r.stop()


def test_presence_releases_after_the_latest_loss_only() -> None:
    """Lost, back, lost again: the first grace is stale; the lease goes only when the second one is over."""
    now, released = [0.0], []
    presence = Presence(5.0, gauge=lambda n: None, release=released.append, leased=lambda: [],
                        clock=lambda: now[0])
    presence.joined("w1")
    presence.left("w1")
    now[0] = 3.0
    assert presence.joined("w1")  # back within the grace: the caller has it said
    now[0] = 4.0
    presence.left("w1")
    now[0] = 6.0
    presence.release_due()
    assert released == [] and presence.next_due() == 9.0
    now[0] = 9.0
    presence.release_due()
    assert released == ["w1"] and presence.pending() == 0 and presence.alive() == []


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "-inf", "86401"])
def test_serve_refuses_a_bad_grace_in_one_line_exit_2(capsys, tmp_path, value) -> None:
    rc, out, err = run_cli(capsys, "serve", "--data", str(tmp_path), f"--lost-worker-grace={value}")
    assert rc == 2 and out == "" and err.count("\n") == 1 and "--lost-worker-grace" in err, err


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf")])
def test_the_config_refuses_a_bad_grace(tmp_path, value) -> None:
    with pytest.raises(ServiceError, match="lost_worker_grace_s"):
        ServiceConfig(data_dir=tmp_path, lost_worker_grace_s=value)


def test_serve_hands_its_grace_to_the_service(spawn_service, endpoint, namespace, data_dir) -> None:
    """``serve --lost-worker-grace 30`` (after the fixture's 0: the last one wins): a token that goes and comes back
    keeps its lease, and the service's log says so."""
    service = spawn_service("--lost-worker-grace", "30")
    ops = Ops(endpoint, namespace, data_dir)
    try:
        ops.wait_up()
        request_id = ops.add()
        keys = ops.keys
        first = transport.open_session(connect=[endpoint])
        token = first.liveliness().declare_token(keys.worker("w9"))
        assert lease(first, keys, worker="w9").request_id == request_id
        token.undeclare()
        first.close()
        again = transport.open_session(connect=[endpoint])
        token = again.liveliness().declare_token(keys.worker("w9"))
        line = wait_for(lambda: "worker w9 back after" in service.log() and service.log(), 15, "the service's line")
        assert "its 1 lease(s) kept" in line and "worker w9 lost" not in line, line
        assert (ops.get(request_id).status, ops.get(request_id).worker_id) == (RequestStatus.LEASED, "w9")
        token.undeclare()
        again.close()
    finally:
        ops.close()
