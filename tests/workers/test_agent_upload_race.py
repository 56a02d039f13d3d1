"""A renewal that reaches the service after the worker's upload committed: the worker goes on renewing while its
upload is out (a long outage must not cost the lease), so one may meet the request that upload just completed."""

from __future__ import annotations

import threading

from storage.catalog import Catalog
from storage.errors import StaleLeaseError
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator import conftest as orchestrator_fixtures
from tests.orchestrator.test_service import new_request

make_service = orchestrator_fixtures.make_service  # its in-process service, for these tests too


def test_a_renewal_refused_after_the_upload_committed_neither_drops_nor_miscounts_the_episode(
        make_service, spawn_worker, data_dir) -> None:
    """The upload's reply comes late (here held past the worker's timeout: a reply lost after the commit) and a
    renewal meets the request the upload completed, refused stale_token. The worker used to take that for a lost
    lease: a WARNING "lease ... lost", no second try (the one the service answers 'duplicate'), "dropping the
    episode" that was stored, and the episode not counted (its --max-episodes overshot)."""
    service = make_service(lease_s=0.6)  # a renewal every 0.2 s
    request, _ = service.queue.enqueue(new_request())
    refused = threading.Event()
    renew, stored = service.queue.renew, service._uploads.on_stored

    def renew_seen(*args, **kw):
        try:
            return renew(*args, **kw)
        except StaleLeaseError:
            refused.set()
            raise

    w = spawn_worker("R", "--timeout", "1", "--max-episodes", "1")

    def late_reply(episode):  # after the commit, before the reply
        wait_for(refused.is_set, message="a renewal to meet the request the upload completed")
        wait_for(lambda: "upload: " in w.log(), message="the worker's first upload attempt to go unanswered")
        stored(episode)

    service.queue.renew, service._uploads.on_stored = renew_seen, late_reply
    assert w.wait(60) == 0, w.log()
    log = w.log()
    assert f"uploaded {request.id}: episode " in log and "(duplicate)" in log, log
    assert "1 uploaded" in log and "dropping the episode" not in log and "lost (" not in log, log
    assert f"renewal of {request.id} refused (stale_token) while its upload is out" in log, log
    assert service.queue.get(request.id).status == RequestStatus.DONE and Catalog(data_dir).count() == 1
