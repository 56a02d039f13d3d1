"""The service on storage that became read-only (a file system remounted read-only after disk errors, a database
file it may only read), and on a disk that refuses an episode for good: a worker's renew and upload are refused
`unavailable` or `internal`, on which it keeps its episode and sends it again -- never `bad_field`, on which it
fails the request and drops the episode -- and a read-only store is an outage that holds every lease."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from orchestrator import messages
from orchestrator.protocol import ErrorCode
from storage.catalog import Catalog
from storage.episode_reader import read_episode
from storage.episode_table import file_path
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, refused, upload
from tests.storage.test_readonly import read_only_database, read_only_queue


def renew(client, keys, grant) -> dict:
    return call(client, keys.renew, messages.RenewRequest(request_id=grant.request_id, token=grant.token,
                                                          worker_id="w1").to_json())


def test_a_read_only_database_refuses_renew_and_upload_as_unavailable_and_holds_the_lease(
        make_service, client, keys, data_dir, monkeypatch, caplog) -> None:
    """Every write the service makes (its queue's, its catalog's) meets SQLITE_READONLY: the worker is told
    `unavailable` for its renew (its lease is not lost) and its upload (its episode is not dropped), and the
    storage is down. The lease's term runs out meanwhile; once the database is writable, the reaper's first
    write gives it a full term instead of expiring it (an attempt counted, the upload then refused as stale),
    and the same bytes go in."""
    with caplog.at_level(logging.INFO, logger="orchestrator"):
        service = make_service(lease_s=2.0)
        request, _ = service.queue.enqueue(new_request())
        grant = lease(client, keys)
        data = episode_bytes(grant)
        with monkeypatch.context() as patch:
            read_only_database(patch)
            read_only_queue(service.queue)
            refused(ErrorCode.UNAVAILABLE, upload, client, keys, grant, data)
            assert service.storage.down_since is not None

            def renewed_past_the_term() -> bool:  # as the worker's Renewer does, each refused
                why = refused(ErrorCode.UNAVAILABLE, renew, client, keys, grant)
                assert "readonly database" in why, why
                return time.time() > grant.expires_at

            wait_for(renewed_past_the_term, message="the end of the lease's term, renewals refused")
            read_only_queue(service.queue, on=False)
        wait_for(lambda: service.storage.down_since is None, message="the reaper to see the storage back")
        body = upload(client, keys, grant, data)
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, done.token, done.attempts) == (
        RequestStatus.DONE, body["episode_id"], grant.token, 0)
    assert Catalog(data_dir).verify(body["episode_id"])
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].startswith("storage unavailable:"), errors


def test_an_upload_the_disk_refuses_for_good_is_internal_not_bad_field(service, client, keys, data_dir) -> None:
    """A failure of the service's own disk that does not pass (here the episode's day folder is a file) is no
    fault of the upload: `internal`, which the worker retries with the same bytes, not `bad_field`, on which
    it would fail the request and drop them. Nothing is stored or counted; once the disk is put right, the
    same upload goes in."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    day = data_dir / Path(file_path(read_episode(data).meta)).parent
    day.parent.mkdir(parents=True, exist_ok=True)
    day.write_bytes(b"")  # where the folder should be
    why = refused(ErrorCode.INTERNAL, upload, client, keys, grant, data)
    assert str(day) in why, why
    held = service.queue.get(request.id)
    assert (held.status, held.token, held.attempts) == (RequestStatus.LEASED, grant.token, 0)
    assert Catalog(data_dir).count() == 0 and service.storage.down_since is None
    day.unlink()
    body = upload(client, keys, grant, data)
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, done.attempts) == (RequestStatus.DONE, body["episode_id"], 0)
