"""Uploads in parts (``orchestrator.upload_parts``) to the service over a real Zenoh client session: each part
answered with the bytes held, nothing written or indexed before the last, which is stored as a whole upload is;
a part of a lease that is not live, or past the upload's end, refused and nothing kept."""

from __future__ import annotations

import hashlib
import threading

import pytest

from orchestrator import messages, protocol
from orchestrator.messages import UploadHeader, UploadPart
from orchestrator.protocol import ErrorCode, ProtocolError
from orchestrator.upload_parts import PartStaging
from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from storage.requests import RequestStatus
from tests.orchestrator.test_service import call, episode_bytes, lease, new_request, refused

PART = 1000


def full_disk_once(catalog) -> list[int]:
    """``catalog.ingest_bytes`` refuses the next ingest as a full disk does; the list it returns records it."""
    real, failed = catalog.ingest_bytes, []

    def ingest(*args, **kw):
        if not failed:
            failed.append(1)
            raise CatalogUnavailableError("database catalog.sqlite: database or disk is full")
        return real(*args, **kw)

    catalog.ingest_bytes = ingest
    return failed


def header_of(grant, data: bytes, worker: str = "w1") -> UploadHeader:
    return UploadHeader.for_payload(data, request_id=grant.request_id, token=grant.token, worker_id=worker)


def send_part(client, keys, header: UploadHeader, data: bytes, offset: int, size: int = PART) -> dict:
    return call(client, keys.upload, data[offset:offset + size], UploadPart.of(header, offset).to_json())


def stored_files(data_dir) -> list:
    return list((data_dir / "episodes").rglob("*.mcap"))


def test_an_upload_in_parts_is_stored_once_its_last_part_comes(service, client, keys, data_dir) -> None:
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    offsets = list(range(0, len(data), PART))
    assert len(offsets) >= 3
    for offset in offsets[:-1]:
        body = send_part(client, keys, header, data, offset)
        assert body == {"request_id": request.id, "received": offset + PART}
        assert Catalog(data_dir).count() == 0 and not stored_files(data_dir)  # nothing written before the last
        assert service.queue.get(request.id).status == RequestStatus.LEASED
    assert send_part(client, keys, header, data, offsets[1]) == {"request_id": request.id,  # a reply lost: again
                                                                 "received": offsets[-1]}
    body = send_part(client, keys, header, data, offsets[-1])
    assert body["request_id"] == request.id and "received" not in body and "duplicate" not in body
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id) == (RequestStatus.DONE, body["episode_id"])
    assert Catalog(data_dir).get(body["episode_id"]).sha256 == hashlib.sha256(data).hexdigest()
    assert service._uploads.parts.held_bytes() == 0
    # The last part again (its reply lost): the episode is stored, intact: a duplicate, no bytes needed.
    assert send_part(client, keys, header, data, offsets[-1]) == {**body, "duplicate": True}
    assert send_part(client, keys, header, data, 0) == {**body, "duplicate": True}
    assert service._uploads.parts.held_bytes() == 0


def test_a_part_past_the_bytes_held_is_answered_with_them_and_not_kept(service, client, keys, data_dir) -> None:
    """A service that restarted holds none of what it was sent: the worker is told to send from there."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    assert send_part(client, keys, header, data, 2 * PART) == {"request_id": request.id, "received": 0}
    assert service._uploads.parts.held_bytes() == 0
    send_part(client, keys, header, data, 0)
    assert send_part(client, keys, header, data, 2 * PART) == {"request_id": request.id, "received": PART}
    assert send_part(client, keys, header, data, PART, len(data))["episode_id"]  # the rest in one part
    assert service.queue.get(request.id).status == RequestStatus.DONE


def test_parts_of_a_lease_that_is_not_live_are_refused_and_nothing_is_kept(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    old = lease(client, keys, worker="slow")
    data = episode_bytes(old, worker="slow")
    header = header_of(old, data, "slow")
    send_part(client, keys, header, data, 0)
    assert service._uploads.parts.held_bytes() == PART and service._uploads._lease_live(header)
    call(client, keys.fail, messages.FailRequest(request_id=old.request_id, token=old.token, worker_id="slow",
                                                 error="boom").to_json())
    assert not service._uploads._lease_live(header)  # (what the sweep asks before it forgets old parts)
    refused(ErrorCode.STALE_TOKEN, send_part, client, keys, header, data, PART)
    assert service._uploads.parts.held_bytes() == 0  # what the lost lease had sent is dropped too
    new = lease(client, keys, worker="fast")
    refused(ErrorCode.STALE_TOKEN, send_part, client, keys, header, data, 0)  # not even a first part
    fresh = episode_bytes(new, worker="fast")
    body = send_part(client, keys, header_of(new, fresh, "fast"), fresh, 0, len(fresh))
    assert body["episode_id"] and Catalog(data_dir).count() == 1


def test_a_part_of_another_upload_of_the_request_starts_it_again(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    other = header_of(grant, data[:-1] + bytes([data[-1] ^ 1]))  # other bytes: another sha256
    service._uploads.parts.replace_after_s = 0.0  # (the other upload went quiet: a worker that restarted)
    send_part(client, keys, other, data, 0)
    send_part(client, keys, other, data, PART)
    assert send_part(client, keys, header_of(grant, data), data, PART)["received"] == 0  # not this upload's
    assert send_part(client, keys, header_of(grant, data), data, 0)["received"] == PART
    assert service._uploads.parts.held_bytes() == PART


def test_parts_whose_bytes_do_not_match_their_header_are_refused_and_nothing_is_stored(service, client, keys,
                                                                                        data_dir) -> None:
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    damaged = data[:PART] + bytes(PART) + data[2 * PART:]
    send_part(client, keys, header, damaged, 0)
    send_part(client, keys, header, damaged, PART)
    refused(ErrorCode.HASH_MISMATCH, send_part, client, keys, header, damaged, 2 * PART, len(data))
    assert Catalog(data_dir).count() == 0 and not stored_files(data_dir)
    assert service._uploads.parts.held_bytes() == 0
    assert service.queue.get(request.id).status == RequestStatus.LEASED  # the worker may send it again
    assert send_part(client, keys, header, data, 0, len(data))["episode_id"]


def test_a_part_that_ends_past_the_upload_or_names_no_place_in_it_is_refused(service, client, keys) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    message = refused(ErrorCode.BAD_FIELD, call, client, keys.upload, data[:PART] + b"x",
                      UploadPart.of(header, len(data) - PART).to_json())
    assert f"offset {len(data) - PART} of size {len(data)}" in message
    for offset in (-1, len(data), True, 1.5):
        raw = protocol.encode({"v": 1, **header.to_dict(), "offset": offset})
        assert "offset" in refused(ErrorCode.BAD_FIELD, call, client, keys.upload, data[:PART], raw)
    assert service._uploads.parts.held_bytes() == 0


def test_a_stored_episode_whose_file_was_lost_is_put_back_from_its_parts_sent_again(service, client, keys,
                                                                                     data_dir) -> None:
    """A repeat in parts of an upload the service stored: with the stored file intact, any part is answered as a
    duplicate; with it lost, the parts are taken again, and the last one puts the file back (as a repeat of a
    whole upload does) before the worker is told it may let go of its bytes."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    body = send_part(client, keys, header, data, 0, len(data))
    path = Catalog(data_dir).get(body["episode_id"]).path
    path.unlink()
    assert send_part(client, keys, header, data, 0)["received"] == PART
    assert send_part(client, keys, header, data, PART, len(data)) == {**body, "duplicate": True}
    assert path.read_bytes() == data


def test_parts_of_a_lease_that_ended_are_dropped_by_the_sweep_after_their_age() -> None:
    now, live = [0.0], {"r1": True, "r2": False}
    staging = PartStaging(max_age_s=10.0, clock=lambda: now[0], live=lambda header: live[header.request_id])
    headers = {r: UploadHeader(request_id=r, token=1, worker_id="w", sha256="0" * 64, size=10) for r in live}
    assert staging.add(UploadPart.of(headers["r1"], 0), b"abcd") == 4
    assert staging.add(UploadPart.of(headers["r2"], 0), b"xyz") == 3
    now[0] = 10.0
    assert staging.add(UploadPart.of(headers["r1"], 4), b"ef") == 6  # touched: its age starts again
    staging.sweep()
    assert staging.held_bytes() == 6 + 3  # none older than 10 s
    now[0] = 20.5
    staging.sweep()  # r2's lease has ended: its parts go; r1's is live: its next part may be slow to come
    assert staging.held_bytes() == 6
    live["r1"] = False
    staging.sweep()
    assert staging.held_bytes() == 0
    with pytest.raises(ProtocolError, match="expected 1 to 10 bytes"):
        staging.add(UploadPart.of(headers["r1"], 0), b"")


def test_a_last_part_whose_store_failed_for_a_passing_reason_stores_the_whole_when_sent_again(service, client, keys,
                                                                                               data_dir) -> None:
    """A full disk for a moment: the last part is answered `unavailable` and the bytes stay held, so the worker
    sends that part alone again (the service used to have forgotten them: it asked for the whole episode again)."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    full_disk_once(service.catalog)
    send_part(client, keys, header, data, 0)
    refused(ErrorCode.UNAVAILABLE, send_part, client, keys, header, data, PART, len(data))
    assert service._uploads.parts.held_bytes() == len(data) and Catalog(data_dir).count() == 0
    body = send_part(client, keys, header, data, PART, len(data))
    assert body["episode_id"] and service.queue.get(request.id).status == RequestStatus.DONE
    assert service._uploads.parts.held_bytes() == 0


def test_a_repeat_of_the_last_part_while_it_is_stored_is_answered_as_stored(service, client, keys, data_dir) -> None:
    """The worker's wait for the last part's reply ran out while the service was storing it: the repeat gets the
    episode (stored, or a duplicate of it), not 'send from the start'."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = header_of(grant, data)
    send_part(client, keys, header, data, 0)
    uploads, decoding, repeat_in = service._uploads, threading.Event(), threading.Event()
    real = uploads._decode

    def first_waits_for_the_repeat(*args, **kw):
        if not decoding.is_set():
            decoding.set()
            assert repeat_in.wait(30)
        else:
            repeat_in.set()
        return real(*args, **kw)

    uploads._decode = first_waits_for_the_repeat
    replies: list[dict] = []
    first = threading.Thread(target=lambda: replies.append(send_part(client, keys, header, data, PART, len(data))))
    first.start()
    assert decoding.wait(30)
    replies.append(send_part(client, keys, header, data, PART, len(data)))
    first.join(30)
    assert len(replies) == 2 and all(r.get("episode_id") == replies[0]["episode_id"] for r in replies), replies
    assert service.queue.get(request.id).status == RequestStatus.DONE and Catalog(data_dir).count() == 1
    assert uploads.parts.held_bytes() == 0


def test_a_part_slower_than_the_staging_age_does_not_age_out_its_own_upload() -> None:
    """Its lease was checked just before: live. (A part taking longer to arrive than max_age_s made the worker
    start again from 0, for ever.)"""
    now = [0.0]
    staging = PartStaging(max_age_s=10.0, clock=lambda: now[0])
    header = UploadHeader(request_id="r1", token=1, worker_id="w", sha256="0" * 64, size=6)
    assert staging.add(UploadPart.of(header, 0), b"abc") == 3
    now[0] = 11.0
    assert staging.add(UploadPart.of(header, 3), b"def") == b"abcdef"


def test_two_uploads_of_other_bytes_under_one_lease_do_not_reset_each_other(service, client, keys, caplog) -> None:
    """Two processes with one worker id: the second's parts are refused (unavailable, sent again later) while the
    first's go on; they used to reset each other's parts, each told 'received 0', for ever, and nothing said why."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    other_data = data[:-1] + bytes([data[-1] ^ 1])
    header, other = header_of(grant, data), header_of(grant, other_data)
    assert send_part(client, keys, header, data, 0)["received"] == PART
    assert "share the id w1" in refused(ErrorCode.UNAVAILABLE, send_part, client, keys, other, other_data, 0)
    assert send_part(client, keys, header, data, PART, len(data))["episode_id"]
    refused(ErrorCode.STALE_TOKEN, send_part, client, keys, other, other_data, 0)  # the whole upload's refusal
    assert "two workers use the id w1" in caplog.text
    assert service.queue.get(request.id).status == RequestStatus.DONE


def test_parts_are_held_up_to_a_total_and_to_what_the_request_can_be(make_service, client, keys) -> None:
    service = make_service(max_upload_bytes=4 * PART)  # at most 16 parts set aside in all
    for _ in range(5):
        service.queue.enqueue(new_request())
    grants = [lease(client, keys, worker=f"w{i}") for i in range(5)]
    headers = [UploadHeader(request_id=g.request_id, token=g.token, worker_id=f"w{i}", sha256="0" * 64,
                            size=4 * PART) for i, g in enumerate(grants)]
    junk = bytes(3 * PART)
    for h in headers[:4]:
        assert call(client, keys.upload, junk, UploadPart.of(h, 0).to_json())["received"] == 3 * PART
    assert service._uploads.parts.held_bytes() == 12 * PART
    assert "at most" in refused(ErrorCode.UNAVAILABLE, call, client, keys.upload, junk,
                                UploadPart.of(headers[4], 0).to_json())
    assert service._uploads.parts.held_bytes() == 12 * PART
    assert f"activecollect_upload_parts_held_bytes {12 * PART}.0" in service.metrics.render()
    for h in headers[:4]:  # every upload let in ends (their bytes are junk: refused, and forgotten)
        refused(ErrorCode.HASH_MISMATCH, call, client, keys.upload, bytes(PART), UploadPart.of(h, 3 * PART).to_json())
    assert service._uploads.parts.held_bytes() == 0


def test_parts_of_an_upload_bigger_than_its_request_can_be_are_refused(service, client, keys) -> None:
    service.queue.enqueue(new_request(steps=5))
    grant = lease(client, keys)
    header = UploadHeader(request_id=grant.request_id, token=grant.token, worker_id="w1", sha256="0" * 64,
                          size=protocol.MAX_UPLOAD_BYTES)
    refused(ErrorCode.TOO_LARGE, call, client, keys.upload, bytes(PART), UploadPart.of(header, 0).to_json())
    assert service._uploads.parts.held_bytes() == 0


def test_a_full_staging_forgets_ended_leases_then_refuses_new_uploads_but_not_those_it_let_in() -> None:
    """Each upload is counted at its whole size from its first part: uploads under way that filled the staging
    between them were each refused their next part, for ever (a review's reproduction)."""
    now, live = [0.0], {"r1": True, "r2": False, "r3": True, "r4": True}
    staging = PartStaging(max_age_s=60.0, clock=lambda: now[0], live=lambda header: live[header.request_id],
                          max_total_bytes=10)
    headers = {r: UploadHeader(request_id=r, token=1, worker_id=r, sha256="0" * 64, size=5) for r in live}
    assert staging.add(UploadPart.of(headers["r1"], 0), b"ab") == 2
    assert staging.add(UploadPart.of(headers["r2"], 0), b"cd") == 2
    now[0] = 1.0
    assert staging.add(UploadPart.of(headers["r3"], 0), b"ef") == 2  # r2's lease ended: its 5 bytes went
    with pytest.raises(ProtocolError, match="10 bytes set aside for uploads in parts, at most 10") as refused:
        staging.add(UploadPart.of(headers["r4"], 0), b"g")  # a new upload waits, nothing kept
    assert refused.value.code == ErrorCode.UNAVAILABLE and staging.held_bytes() == 4
    assert staging.add(UploadPart.of(headers["r1"], 2), b"xyz") == b"abxyz"  # one let in ends
    assert staging.add(UploadPart.of(headers["r3"], 2), b"uvw") == b"efuvw"
    staging.drop(headers["r1"])
    assert staging.add(UploadPart.of(headers["r4"], 0), b"g") == 1  # room again
