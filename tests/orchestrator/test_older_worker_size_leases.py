"""An older worker (its lease request gives no ``image_size``) refused for recording at another frame size than the
catalog's is refused its next leases, saying why, rather than leased, collecting and refused again forever; the mark
goes when it says its size (upgraded) or when its liveliness token comes or goes (restarted, perhaps at the
catalog's ``--size``). Older workers are simulated as ``test_service_older_worker`` does: their lease requests."""

from __future__ import annotations

import pytest

from orchestrator import messages, transport, uploads
from orchestrator.protocol import ErrorCode
from storage.catalog import Catalog
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, refused, upload
from tests.orchestrator.test_service_older_worker import older_lease


def sized_catalog(service, client, keys, requests: int) -> None:
    """``requests`` queued, and a first episode that makes the catalog's frames 16 px."""
    for _ in range(requests + 1):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))


def refused_for_size(client, keys, worker: str, size: int = 24) -> messages.LeaseGrant:
    """An older worker leases, records at ``size`` px and is refused for it; its grant."""
    grant = older_lease(client, keys, worker)
    refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, worker, size), worker=worker)
    return grant


def refusals(service, reason: str) -> float:
    return service.metrics.registry.get_sample_value(
        "activecollect_refusals_total", {"reason": reason, "source": "worker"}) or 0.0


def test_after_its_first_size_refusal_an_older_worker_is_refused_leases_saying_why(service, client, keys) -> None:
    sized_catalog(service, client, keys, 3)
    grant = refused_for_size(client, keys, "old")
    queued = {r.id: r.token for r in service.queue.list(RequestStatus.QUEUED)}
    assert grant.request_id in queued and len(queued) == 3
    before = refusals(service, "bad_field")
    for _ in range(2):  # no lease, nothing to collect: every time
        message = refused(ErrorCode.BAD_FIELD, call, client, keys.lease,
                          messages.LeaseRequest(worker_id="old").to_json())
        assert "worker old records 24px frames; this catalog holds 16px episodes" in message, message
        assert "upgrade it or start it with --size 16" in message, message
    assert {r.id: r.token for r in service.queue.list(RequestStatus.QUEUED)} == queued  # nothing leased
    assert service.queue.get(grant.request_id).attempts == 0
    assert refusals(service, "bad_field") == before + 2  # counted as the workers' refusals


def test_other_workers_are_leased_to_as_before(service, client, keys, data_dir) -> None:
    """A worker that says its size, and an older one never refused (at the catalog's size), are unaffected."""
    sized_catalog(service, client, keys, 3)
    refused_for_size(client, keys, "old")
    refused(ErrorCode.BAD_FIELD, older_lease, client, keys, "old")
    grant = lease(client, keys, worker="new", image_size=24)
    assert grant.image_size == 16
    assert "duplicate" not in upload(client, keys, grant, episode_bytes(grant, "new"), worker="new")
    right = older_lease(client, keys, "old16")
    assert "duplicate" not in upload(client, keys, right, episode_bytes(right, "old16"), worker="old16")
    assert Catalog(data_dir).count() == 3


def test_an_upgraded_worker_that_says_its_size_is_leased_to_and_forgotten(service, client, keys, data_dir) -> None:
    sized_catalog(service, client, keys, 3)
    refused_for_size(client, keys, "old")
    refused(ErrorCode.BAD_FIELD, older_lease, client, keys, "old")
    grant = lease(client, keys, worker="old", image_size=24)  # upgraded, same --id
    assert grant.image_size == 16
    assert "duplicate" not in upload(client, keys, grant, episode_bytes(grant, "old"), worker="old")
    again = older_lease(client, keys, "old")  # forgotten: an older build again is leased to (and judged by its upload)
    assert service.queue.get(again.request_id).status == RequestStatus.LEASED


@pytest.mark.parametrize("grace_s", [0.0, 30.0])  # back within its grace too: a restart is quicker than a grace
def test_the_mark_goes_with_the_workers_liveliness_token(make_service, client, keys, endpoint, data_dir,
                                                         grace_s) -> None:
    service = make_service(lost_worker_grace_s=grace_s)
    sized_catalog(service, client, keys, 3)
    first = transport.open_session(connect=[endpoint])
    token = first.liveliness().declare_token(keys.worker("old"))
    wait_for(lambda: "old" in service.workers(), message="the service sees the worker")
    refused_for_size(first, keys, "old")
    refused(ErrorCode.BAD_FIELD, older_lease, first, keys, "old")
    token.undeclare()  # it stops ...
    first.close()
    wait_for(lambda: "old" not in service.workers(), message="the service sees the worker go")
    again = transport.open_session(connect=[endpoint])  # ... and is started again with --size 16, the same --id
    try:
        token = again.liveliness().declare_token(keys.worker("old"))
        grant = older_lease(again, keys, "old")
        assert "duplicate" not in upload(again, keys, grant, episode_bytes(grant, "old"), worker="old")
        assert Catalog(data_dir).count() == 2
        token.undeclare()
    finally:
        again.close()


def test_the_older_workers_kept_are_bounded(service, client, keys, monkeypatch) -> None:
    """The newest ``SIZELESS_MAX`` are kept: a worker forgotten is leased to again (and refused for its size again)."""
    monkeypatch.setattr(uploads, "SIZELESS_MAX", 1)
    sized_catalog(service, client, keys, 3)
    refused_for_size(client, keys, "old")
    refused_for_size(client, keys, "other")
    refused(ErrorCode.BAD_FIELD, older_lease, client, keys, "other")
    assert len(service._uploads._older) == 1
    refused_for_size(client, keys, "old")
