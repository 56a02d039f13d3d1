"""An upload racing every other change of its request: the lease's expiry, the worker's own fail / release /
renew, the loss of its liveliness, an operator's cancel / prioritize. Each change lands between the upload's
lease check and its ingest (the widest window: the MCAP is read in between), over the real Zenoh keys. The end
state is one the lifecycle allows, the episode is stored at most once, a done request has exactly its one
episode, and the reply tells the worker the truth."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from orchestrator import messages
from orchestrator.messages import AdminRequest
from orchestrator.protocol import ErrorCode, ProtocolError
from storage.catalog import Catalog
from storage.requests import RequestStatus
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, upload

_Q, _D, _C = RequestStatus.QUEUED, RequestStatus.DONE, RequestStatus.CANCELLED


def _ref(grant) -> dict:
    return {"request_id": grant.request_id, "token": grant.token, "worker_id": "w1"}


RACES: dict[str, tuple[Callable, RequestStatus | None, int]] = {
    # what happens in the window: (the change, the status after it if the upload loses, attempts after)
    "expire": (lambda s, c, k, g: s.queue.expire_leases(now=time.time() + 3600), _Q, 1),
    "worker_lost": (lambda s, c, k, g: s._worker_lost("w1"), _Q, 1),
    "fail": (lambda s, c, k, g: call(c, k.fail, messages.FailRequest(**_ref(g), error="x").to_json()), _Q, 1),
    "release": (lambda s, c, k, g: call(c, k.release, messages.ReleaseRequest(**_ref(g)).to_json()), _Q, 0),
    "cancel": (lambda s, c, k, g: call(c, k.admin("queue.cancel"), AdminRequest(
        op="queue.cancel", args={"id": g.request_id}).to_json()), _C, 0),
    "prioritize": (lambda s, c, k, g: call(c, k.admin("queue.prioritize"), AdminRequest(
        op="queue.prioritize", args={"id": g.request_id, "priority": 9.0}).to_json()), None, 0),
    "renew": (lambda s, c, k, g: call(c, k.renew, messages.RenewRequest(**_ref(g)).to_json()), None, 0),
}


@pytest.mark.parametrize("race", sorted(RACES))
def test_an_upload_racing_a_change_of_its_request_ends_in_a_legal_state_told_truly(service, client, keys, data_dir,
                                                                                  monkeypatch, race) -> None:
    change, lost_status, attempts = RACES[race]
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    handler, changed = service._uploads, []
    real_decode = handler._decode

    def change_in_the_window(raw, header, req):  # after the lease check, before the ingest
        changed.append(change(service, client, keys, grant))
        return real_decode(raw, header, req)

    monkeypatch.setattr(handler, "_decode", change_in_the_window)
    try:
        reply, code = upload(client, keys, grant, data), None
    except ProtocolError as exc:
        reply, code = None, exc.code
    after, catalog = service.queue.get(request.id), Catalog(data_dir)
    files = list((data_dir / "episodes").rglob("*.mcap"))
    assert changed
    if lost_status is None:  # the change leaves the lease live: the upload completes it
        assert code is None and (after.status, after.episode_id) == (_D, reply["episode_id"])
        assert [e.episode_id for e in catalog.list()] == [reply["episode_id"]] and len(files) == 1
        assert catalog.get(reply["episode_id"]).request_id == request.id
    else:  # the lease ended first: refused as stale, nothing stored, the worker drops the episode
        assert code == ErrorCode.STALE_TOKEN, (code, reply)
        assert (after.status, after.episode_id, catalog.count(), files) == (lost_status, None, 0, [])
    assert (after.attempts, after.token) == (attempts, 1)
    if lost_status == _Q:  # the next lease is a new one: the old token is fenced off for good
        again = lease(client, keys, worker="w2")
        assert (again.request_id, again.token) == (request.id, 2)
        with pytest.raises(ProtocolError) as stale:
            upload(client, keys, grant, data)
        assert stale.value.code == ErrorCode.STALE_TOKEN and Catalog(data_dir).count() == 0


def test_the_bytes_of_one_lease_uploaded_under_the_next_are_refused_and_stored_once(service, client, keys,
                                                                                    data_dir) -> None:
    """w1's lease expired before its upload; the request went back and w1 leased it again (token 2). The episode
    of token 1 is not what token 2 asked for (its seed): refused under token 2, stale under token 1, never stored;
    the episode of token 2 is stored once, and completes the request."""
    request, _ = service.queue.enqueue(new_request())
    first = lease(client, keys)
    old = episode_bytes(first)
    service.queue.expire_leases(now=time.time() + 3600)
    second = lease(client, keys)
    assert (second.request_id, second.token) == (request.id, 2)
    with pytest.raises(ProtocolError) as info:
        upload(client, keys, second, old)
    assert info.value.code == ErrorCode.BAD_FIELD and "seed" in info.value.message
    with pytest.raises(ProtocolError) as info:
        upload(client, keys, first, old)
    assert info.value.code == ErrorCode.STALE_TOKEN and Catalog(data_dir).count() == 0
    body = upload(client, keys, second, episode_bytes(second))
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, done.token) == (_D, body["episode_id"], 2)
    assert [e.episode_id for e in Catalog(data_dir).list()] == [body["episode_id"]]
