"""An older worker (its lease request gives no ``image_size``, so its grant names none) that records at a frame size
other than the catalog's: its upload is refused saying what to do, and its request goes back to the
queue with no attempt counted; the service warns once per worker. Its size is read from its metadata: its upload
is bounded by the catalog's size as any other, and not inflated."""

from __future__ import annotations

import logging

import pytest

from orchestrator import messages
from orchestrator.protocol import ErrorCode
from storage.catalog import Catalog
from storage.episode_reader import decoded_limit
from storage.errors import QueueUnavailableError
from storage.requests import RequestStatus
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, refused, upload
from workers.collect import collect_episode


def older_lease(client, keys, worker: str) -> messages.LeaseGrant:
    """A lease as a worker from before ``image_size`` asks for it: the field is not sent, and not answered."""
    body = call(client, keys.lease, messages.LeaseRequest(worker_id=worker).to_json())
    assert "image_size" not in body["grant"]
    return messages.LeaseGrant.from_dict(body["grant"])


def fail(client, keys, grant: messages.LeaseGrant, worker: str, error: str) -> dict:
    return call(client, keys.fail, messages.FailRequest(request_id=grant.request_id, token=grant.token,
                                                        worker_id=worker, error=error).to_json())


@pytest.mark.parametrize("size, steps", [(24, 5), (64, 50)])  # the second inflates past what 16 px frames need
def test_an_older_workers_upload_of_another_size_is_refused_saying_so_and_its_request_is_queued_uncharged(
        service, client, keys, data_dir, caplog, size, steps) -> None:
    for _ in range(3):
        service.queue.enqueue(new_request(steps=steps))
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))  # the catalog's frames are 16 px from now on
    grant = older_lease(client, keys, "old")
    with caplog.at_level(logging.WARNING, logger="orchestrator.uploads"):
        message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, "old", size),
                          worker="old")
    assert f"worker old records {size}px frames; this catalog holds 16px episodes" in message, message
    assert "upgrade it or start it with --size 16" in message, message
    request = service.queue.get(grant.request_id)
    assert (request.status, request.attempts) == (RequestStatus.QUEUED, 0)  # given back before the reply
    refused(ErrorCode.STALE_TOKEN, fail, client, keys, grant, "old", f"upload refused: {message}")  # the worker's own
    assert service.queue.get(grant.request_id).attempts == 0
    assert Catalog(data_dir).count() == 1
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "old" in warned[0].getMessage() and "--size 16" in warned[0].getMessage()


def test_the_service_warns_once_per_older_worker_not_per_refusal(service, client, keys, caplog) -> None:
    """Its next lease requests are refused too (``test_older_worker_size_leases``), without another line."""
    for _ in range(5):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))
    with caplog.at_level(logging.WARNING, logger="orchestrator.uploads"):
        for worker in ("old", "other"):
            grant = older_lease(client, keys, worker)
            refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, worker, 24), worker=worker)
            assert service.queue.get(grant.request_id).attempts == 0
            for _ in range(2):
                refused(ErrorCode.BAD_FIELD, older_lease, client, keys, worker)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert [w.split()[1] for w in warned] == ["old", "other"], warned
    assert "records 24px frames, not this catalog's 16px" in warned[0] and "--size 16" in warned[0]


def test_an_older_worker_at_the_catalogs_size_is_stored_as_before(service, client, keys, data_dir) -> None:
    for _ in range(2):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))
    grant = older_lease(client, keys, "old")
    assert "duplicate" not in upload(client, keys, grant, episode_bytes(grant, "old"), worker="old")
    assert service.queue.get(grant.request_id).status == RequestStatus.DONE and Catalog(data_dir).count() == 2


def test_a_lease_granted_before_the_catalog_had_a_size_gives_its_request_back_uncharged(service, client, keys,
                                                                                       caplog) -> None:
    """A worker that says its size leased while the catalog was empty (its grant names none: it records at its own,
    24 px); another worker's 16 px episode fixed the size meanwhile. No older worker: no warning."""
    for _ in range(3):
        service.queue.enqueue(new_request())
    early = lease(client, keys, worker="early", image_size=24)
    assert early.image_size == 0
    other = lease(client, keys, worker="w1", image_size=16)
    upload(client, keys, other, episode_bytes(other))  # 16 px from now on
    with caplog.at_level(logging.WARNING, logger="orchestrator.uploads"):
        message = refused(ErrorCode.BAD_FIELD, upload, client, keys, early, episode_bytes(early, "early", 24),
                          worker="early")
    assert "worker early recorded 24px frames, its own size: its lease was granted while the catalog held no " \
           "episode, and it holds 16px episodes since" in message, message
    request = service.queue.get(early.request_id)
    assert (request.status, request.attempts) == (RequestStatus.QUEUED, 0)
    assert not [r for r in caplog.records if r.levelno == logging.WARNING]
    again = lease(client, keys, worker="early", image_size=24)
    assert again.image_size == 16  # its next lease names the catalog's size


def test_an_older_workers_upload_is_bounded_by_the_catalogs_frame_size_as_any_other(service, client, keys) -> None:
    """Its size is checked from its metadata, before a chunk is inflated: a lease that names no size is no way to
    make the service take more than an episode of the catalog's size (declared bigger, its first part is refused)."""
    for _ in range(2):
        service.queue.enqueue(new_request(steps=5))
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))
    grant = older_lease(client, keys, "old")
    header = messages.UploadHeader(request_id=grant.request_id, token=grant.token, worker_id="old",
                                   sha256="0" * 64, size=decoded_limit(5, 16) + 1)
    part = messages.UploadPart.of(header, 0).to_json()
    refused(ErrorCode.TOO_LARGE, call, client, keys.upload, bytes(1000), part)


def test_a_refusal_whose_request_cannot_be_given_back_now_is_unavailable(service, client, keys,
                                                                          monkeypatch) -> None:
    """The queue cannot be written (a full disk): the worker is told to send it again (``unavailable``) and its
    request stays leased; the next try gives it back and is refused for its size."""
    for _ in range(2):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))
    grant = older_lease(client, keys, "old")
    real, full = service.queue.release, []

    def release(*args, **kw):
        if not full:
            full.append(1)
            raise QueueUnavailableError("database catalog.sqlite: database or disk is full")
        return real(*args, **kw)

    monkeypatch.setattr(service.queue, "release", release)
    data = episode_bytes(grant, "old", 24)
    assert "disk is full" in refused(ErrorCode.UNAVAILABLE, upload, client, keys, grant, data, worker="old")
    assert service.queue.get(grant.request_id).status == RequestStatus.LEASED
    refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, data, worker="old")
    request = service.queue.get(grant.request_id)
    assert (request.status, request.attempts) == (RequestStatus.QUEUED, 0)


def test_a_size_fixed_by_another_process_after_the_service_last_read_it_is_caught_at_the_ingest(
        service, client, keys, data_dir, monkeypatch) -> None:
    """The service reads the catalog's size at most once a second while it is unknown: an offline ``collect`` that
    fixed it since is found when the catalog refuses the episode, and the request is given back all the same."""
    for _ in range(2):
        service.queue.enqueue(new_request())
    grant = older_lease(client, keys, "old")
    monkeypatch.setattr(service._uploads, "frame_size", lambda: 0)  # not read again since the catalog was empty
    Catalog(data_dir).add_episode(collect_episode(start_state=grant.start_state, policy="push", seed=1, steps=5,
                                                  image_size=16))  # another process: 16 px from now on
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, "old", 24), worker="old")
    assert "records 24px frames; this catalog holds 16px episodes" in message, message
    request = service.queue.get(grant.request_id)
    assert (request.status, request.attempts) == (RequestStatus.QUEUED, 0)


def test_an_older_workers_upload_at_the_catalogs_size_refused_for_another_reason_is_charged_as_before(
        service, client, keys) -> None:
    """Only a size the catalog does not hold gives a request back uncharged: the catalog's other refusals of the
    upload itself (here its episode id indexed with other bytes) are the worker's, as under any lease."""
    for _ in range(2):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    stored = upload(client, keys, first, episode_bytes(first))
    grant = older_lease(client, keys, "old")
    data = episode_bytes(grant, "old", episode_id=stored["episode_id"])
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, data, worker="old")
    assert "already indexed" in message and "px" not in message, message
    request = service.queue.get(grant.request_id)
    assert (request.status, request.token) == (RequestStatus.LEASED, grant.token)  # its worker's fail charges it


def test_an_older_workers_lease_from_before_a_restart_is_refused_without_claiming_its_lease_named_a_size(
        make_service, client, keys) -> None:
    """The leases granted without a size are remembered in memory: after a restart the upload is refused as any
    other of another size, an attempt counted (see README "Upgrading"), and its words do not say that the lease
    named the size (an older worker's never does)."""
    service = make_service()
    for _ in range(2):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=16)
    upload(client, keys, first, episode_bytes(first))
    grant = older_lease(client, keys, "old")
    service.stop()
    service = make_service()
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, "old", 24), worker="old")
    assert "24px frames; this catalog holds 16px episodes" in message and "lease named" not in message, message
    assert service.queue.get(grant.request_id).status == RequestStatus.LEASED  # its worker's fail charges it
