"""Uploads to orchestrator.service over a real Zenoh client session: stored, indexed and completed once, and
every upload that is not exactly what its lease asked for refused before anything is written."""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
import sys
import threading

import pytest

from orchestrator import messages, protocol, uploads
from orchestrator.messages import LeaseGrant
from orchestrator.protocol import ErrorCode
from orchestrator.transport import Incoming
from storage.catalog import Catalog
from storage.episode_reader import read_episode
from storage.quarantine import quarantine_path
from storage.requests import RequestStatus
from tests.conftest import wait_for
from tests.orchestrator.test_service import (DEFAULT_PHYSICS, call, episode_bytes, lease, new_request, refused,
                                             upload)
from tests.storage.test_episodes import _episode_like_mcap


def test_upload_stores_indexes_and_completes_once(service, client, keys, data_dir) -> None:
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    assert body["request_id"] == request.id and "duplicate" not in body
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id) == (RequestStatus.DONE, body["episode_id"])
    row = Catalog(data_dir).get(body["episode_id"])
    assert row.sha256 == hashlib.sha256(data).hexdigest() and row.request_id == request.id
    again = upload(client, keys, grant, data)  # e.g. the reply was lost and the worker retried
    assert again == {**body, "duplicate": True}
    refused(ErrorCode.BAD_FIELD, call, client, keys.upload, b"junk",  # the right header, other bytes
            protocol.encode({"v": 1, **messages.UploadHeader.for_payload(data, request_id=grant.request_id,
                                                                         token=grant.token, worker_id="w1").to_dict()}))
    assert Catalog(data_dir).count() == 1
    assert len(list((data_dir / "episodes").rglob("*.mcap"))) == 1


def test_concurrent_identical_uploads_store_one_episode(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    results: list[dict] = []
    threads = [threading.Thread(target=lambda: results.append(upload(client, keys, grant, data))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 4 and len({r["episode_id"] for r in results}) == 1
    assert sum(1 for r in results if not r.get("duplicate")) == 1
    assert Catalog(data_dir).count() == 1


def test_stale_token_upload_is_refused_before_anything_is_written(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    old = lease(client, keys, worker="slow")
    data = episode_bytes(old, worker="slow")
    call(client, keys.fail, messages.FailRequest(request_id=old.request_id, token=old.token, worker_id="slow",
                                                 error="boom").to_json())
    new = lease(client, keys, worker="fast")
    assert new.token == old.token + 1
    message = refused(ErrorCode.STALE_TOKEN, upload, client, keys, old, data, worker="slow")
    assert "token 1" in message
    upload(client, keys, new, episode_bytes(new, worker="fast"), worker="fast")
    assert service.queue.get(new.request_id).worker_id == "fast"
    assert Catalog(data_dir).count() == 1


def test_a_second_upload_of_one_lease_under_the_same_id_names_two_workers_sharing_the_id(service, client, keys,
                                                                                           data_dir, caplog) -> None:
    """Two worker processes given one --id are handed the same lease (the service gives a worker the lease it
    holds again) and both collect it: the second upload, other bytes under the same token and id, can only come
    from another process with that id. It is refused as stale, saying so, and the service logs it as an error."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys, worker="X")
    first, second = episode_bytes(grant, worker="X"), episode_bytes(grant, worker="X")
    assert first != second
    assert not upload(client, keys, grant, first, worker="X").get("duplicate")
    assert upload(client, keys, grant, first, worker="X")["duplicate"]  # its own retry: acknowledged
    with caplog.at_level(logging.ERROR, logger="orchestrator.uploads"):
        message = refused(ErrorCode.STALE_TOKEN, upload, client, keys, grant, second, worker="X")
    assert "another worker with the id X has already uploaded other bytes for this lease (token 1)" in message
    assert "two workers share the id X: give each its own --id" in message
    assert [r.getMessage().split(":")[0] for r in caplog.records] == ["two workers use the id X"]
    assert Catalog(data_dir).count() == 1 and service.queue.get(grant.request_id).status == RequestStatus.DONE


@pytest.mark.parametrize("damage", ["truncated", "flipped", "not_mcap"])
def test_corrupt_uploads_are_refused_and_nothing_is_indexed(service, client, keys, data_dir, damage) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = bytearray(episode_bytes(grant))
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "flipped":
        data[len(data) // 2] ^= 0xFF
    else:
        data = bytearray(b"hello, this is not an episode" * 10)
    message = refused(ErrorCode.CORRUPT_EPISODE, upload, client, keys, grant, bytes(data))
    assert message
    assert Catalog(data_dir).count() == 0
    assert not list((data_dir / "episodes").rglob("*")) or not list((data_dir / "episodes").rglob("*.mcap"))
    assert service.queue.get(grant.request_id).status == RequestStatus.LEASED  # still the worker's to fix


def test_hash_size_and_provenance_mismatches_are_refused(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    other, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    refused(ErrorCode.HASH_MISMATCH, upload, client, keys, grant, data, sha256="0" * 64)
    refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, data, size=len(data) + 1)
    foreign = LeaseGrant.from_dict({**grant.to_dict(), "request_id": other.id})
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(foreign))
    assert "provenance" in message
    assert Catalog(data_dir).count() == 0


@pytest.mark.parametrize("change, words", [
    (lambda g: {"shape": "L", "start_state": {**g.start_state, "shape": "L"}}, "found 'L'"),
    (lambda g: {"steps": g.steps + 1}, "steps, found"),
    (lambda g: {"policy": "random_waypoints", "policy_params": {}}, "expected policy 'push'"),
    (lambda g: {"start_state": {**g.start_state, "agent": [101.0, 100.0]}}, "start_state.agent[0] differs"),
    (lambda g: {"worker": "someone-else"}, "expected worker_id 'w1'"),
    (lambda g: {"seed": g.seed + 1}, "expected the lease's seed"),
    (lambda g: {"meta": {"physics": {"mass": 1e308}}}, "physics.mass: expected a finite number in [0.2, 5]"),
    (lambda g: {"meta": {"physics": {"mass": 1.0, "gravity": -5.0}}}, "found gravity (outside the task space)"),
    (lambda g: {"meta": {"created": "9999-99-99"}}, "created: expected an ISO 8601 time, found '9999-99-99'"),
    (lambda g: {"meta": {"physics": {**DEFAULT_PHYSICS, "mass": DEFAULT_PHYSICS["mass"] * 1.5}}},
     "physics.mass differs"),
])
def test_an_upload_that_is_not_what_the_request_asked_for_is_refused(service, client, keys, data_dir,
                                                                     change, words) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    asked = change(grant)
    worker, meta = asked.pop("worker", "w1"), asked.pop("meta", {})
    wrong = episode_bytes(LeaseGrant.from_dict({**grant.to_dict(), **asked}), worker=worker, **meta)
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, wrong)
    assert "provenance" in message and words in message, message
    assert Catalog(data_dir).count() == 0
    assert service.queue.get(grant.request_id).status == RequestStatus.LEASED
    assert "duplicate" not in upload(client, keys, grant, episode_bytes(grant))  # the right one still goes in
    assert service.queue.get(grant.request_id).status == RequestStatus.DONE


def test_an_upload_of_another_frame_size_than_the_catalogs_is_refused(service, client, keys, data_dir) -> None:
    for _ in range(3):
        service.queue.enqueue(new_request())
    first = lease(client, keys, image_size=24)
    assert first.image_size == 0  # an empty catalog: the worker's own size
    upload(client, keys, first, episode_bytes(first))  # the catalog's frames are 16 px from now on
    grant = lease(client, keys, image_size=24)
    assert grant.image_size == 16  # what a worker that says its own size records at
    older = call(client, keys.lease, messages.LeaseRequest(worker_id="w2").to_json())["grant"]
    assert "image_size" not in older  # workers from before the field refuse unknown fields: not sent to them
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, size=24))
    assert "24px frames; this catalog holds 16px episodes" in message
    assert Catalog(data_dir).count() == 1 and service.queue.get(grant.request_id).status == RequestStatus.LEASED


def test_a_first_upload_at_a_size_no_model_trains_on_is_refused_and_changes_nothing(service, client, keys,
                                                                                   data_dir) -> None:
    """It would fix the empty catalog's size (a worker from before ``--size`` was checked can send one)."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys, image_size=12)
    assert grant.image_size == 0  # an empty catalog: the worker's own size
    message = refused(ErrorCode.BAD_FIELD, upload, client, keys, grant, episode_bytes(grant, size=12))
    assert "12px frames; the first episode fixes this catalog's frame size, which must be a multiple of 8 " \
           "from 16 to 1024" in message, message
    catalog = Catalog(data_dir)
    assert catalog.count() == 0 and catalog.frame_size() is None
    assert [p for p in catalog.episodes_dir.rglob("*") if p.is_file()] == []
    assert service.queue.get(grant.request_id).status == RequestStatus.LEASED
    assert "duplicate" not in upload(client, keys, grant, episode_bytes(grant))  # 16 px still goes in
    assert catalog.frame_size() == 16


def test_an_upload_that_would_inflate_past_what_the_request_needs_is_refused_before(service, client, keys,
                                                                                    data_dir) -> None:
    """Its frames are the catalog's size, and a chunk holds 32 MiB more (an episode that says another size is refused
    from its metadata: the test above)."""
    for _ in range(2):
        service.queue.enqueue(new_request())
    first = lease(client, keys)
    upload(client, keys, first, episode_bytes(first))  # the catalog holds 16 px frames from now on
    grant = lease(client, keys)
    data = _episode_like_mcap(read_episode(episode_bytes(grant)), pad=32 << 20)  # in a small file
    assert len(data) < 1 << 20
    message = refused(ErrorCode.TOO_LARGE, upload, client, keys, grant, data)
    assert "inflates to" in message and "frames need at most" in message, message
    assert Catalog(data_dir).count() == 1 and service.queue.get(grant.request_id).status == RequestStatus.LEASED


def test_oversized_upload_is_refused(make_service, client, keys, data_dir) -> None:
    service = make_service(max_upload_bytes=1000)
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    refused(ErrorCode.TOO_LARGE, upload, client, keys, grant, episode_bytes(grant))
    assert Catalog(data_dir).count() == 0


def test_every_refused_upload_is_counted_and_published_once(make_service, client, keys) -> None:
    """uploads_total{result="refused"} and the episode.rejected events agree with refusals_total, whichever
    check refused: the header, the request, the size, the hash (before the lease is looked at) or later ones."""
    service = make_service(max_upload_bytes=1 << 20)
    events: list[dict] = []
    sub = client.declare_subscriber(keys.events("episode.rejected"),
                                    lambda s: events.append(json.loads(s.payload.to_bytes())["data"]))
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    refusals = {
        ErrorCode.BAD_JSON: lambda: call(client, keys.upload, data, b"{not json"),
        ErrorCode.UNKNOWN_REQUEST: lambda: upload(client, keys, grant, data, request_id="r-no-such-request"),
        ErrorCode.TOO_LARGE: lambda: upload(client, keys, grant, data, size=(1 << 20) + 1),
        ErrorCode.BAD_FIELD: lambda: upload(client, keys, grant, data, size=len(data) + 1),
        ErrorCode.HASH_MISMATCH: lambda: upload(client, keys, grant, data, sha256="0" * 64),
        ErrorCode.STALE_TOKEN: lambda: upload(client, keys, grant, data, token=grant.token + 1),
        ErrorCode.CORRUPT_EPISODE: lambda: upload(client, keys, grant, data[: len(data) // 2]),
    }
    for code, send in refusals.items():
        refused(code, send)
    assert "duplicate" not in upload(client, keys, grant, data)

    def sample(name: str, **labels: str) -> float:
        return service.metrics.registry.get_sample_value(f"activecollect_{name}", labels) or 0.0

    assert sample("uploads_total", result="refused") == len(refusals)
    assert all(sample("refusals_total", reason=code.value, source="worker") == 1 for code in refusals)
    assert sample("uploads_total", result="stored") == 1
    wait_for(lambda: len(events) >= len(refusals), message="an episode.rejected event for each refusal")
    sub.undeclare()
    assert sorted(e["error"] for e in events) == sorted(code.value for code in refusals)
    assert [e["request_id"] for e in events if e["error"] == "bad_json"] == [None]  # whose is unknown
    assert {e["request_id"] for e in events if e["error"] == "hash_mismatch"} == {grant.request_id}


@pytest.mark.parametrize("damage", ["deleted", "truncated"])
def test_a_repeated_upload_puts_back_a_file_lost_since_before_it_is_acknowledged(service, client, keys, data_dir,
                                                                               damage) -> None:
    """The worker sends again when the first reply was lost; if the stored file was lost or damaged meanwhile,
    its bytes are the last intact copy: they restore the file before the worker is told it can drop them."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    path = Catalog(data_dir).get(body["episode_id"]).path
    if damage == "deleted":
        path.unlink()
    else:
        path.write_bytes(data[:-10])

    assert upload(client, keys, grant, data) == {**body, "duplicate": True}

    assert path.read_bytes() == data
    assert Catalog(data_dir).verify(body["episode_id"])


def test_a_repeated_upload_does_not_end_a_quarantine(service, client, keys, data_dir) -> None:
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    catalog = Catalog(data_dir)
    catalog.quarantine(body["episode_id"], "operator: wrong object")

    assert upload(client, keys, grant, data) == {**body, "duplicate": True}

    row = catalog.get(body["episode_id"])
    assert row.quarantined == "operator: wrong object" and not row.path.exists()


def test_a_repeated_upload_keeps_the_bytes_of_an_episode_lost_then_quarantined(service, client, keys,
                                                                                data_dir) -> None:
    """The stored file was lost, then a training job quarantined the episode (no file to move: nothing kept). The
    worker's repeat is the last intact copy: acknowledged, its bytes are kept in quarantine/, the quarantine stands,
    and `episodes restore` brings the episode back."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    catalog = Catalog(data_dir)
    row = catalog.get(body["episode_id"])
    row.path.unlink()
    reason = "found by a training job: the file is missing"
    assert catalog.quarantine(row.episode_id, reason, only_if_damaged=True).quarantined == reason
    kept = data_dir / quarantine_path(row.path.relative_to(data_dir).as_posix())
    assert not kept.exists()

    assert upload(client, keys, grant, data) == {**body, "duplicate": True}

    assert catalog.get(row.episode_id).quarantined == reason and not row.path.exists()
    assert kept.read_bytes() == data and catalog.snapshot().ids == []
    restored = catalog.restore(row.episode_id)
    assert restored.quarantined == "" and not kept.exists()
    assert hashlib.sha256(row.path.read_bytes()).hexdigest() == row.sha256 == hashlib.sha256(data).hexdigest()
    assert catalog.verify(row.episode_id).episode_id == row.episode_id


def test_a_repeat_whose_lost_file_cannot_be_put_back_is_not_acknowledged(service, client, keys, data_dir) -> None:
    """Acknowledged, the worker would drop the last intact copy: it is refused (the worker sends it again)."""
    service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    path = Catalog(data_dir).get(body["episode_id"]).path
    path.unlink()
    path.parent.rmdir()
    path.parent.write_text("a file where the day's folder was")  # the restore cannot be written

    message = refused(ErrorCode.INTERNAL, upload, client, keys, grant, data)

    assert "restoring it from this upload failed" in message
    path.parent.unlink()
    assert upload(client, keys, grant, data) == {**body, "duplicate": True} and path.read_bytes() == data


def test_an_operators_quarantine_that_commits_while_a_repeat_is_checked_stands(service, client, keys, data_dir,
                                                                            monkeypatch) -> None:
    """The first upload was acknowledged, its reply lost; the worker sends it again, and an operator's
    `activecollect episodes quarantine` commits just after the repeat read the episode's row (not quarantined
    then) and before the file was looked at (gone: moved to quarantine/). The repeat is acknowledged (the
    worker must not collect it again) and the quarantine stands: the file stays in quarantine/, the row stays
    quarantined, nothing is put back into episodes/ and nothing is indexed twice."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    body = upload(client, keys, grant, data)
    catalog = Catalog(data_dir)
    row = catalog.get(body["episode_id"])
    kept = data_dir / quarantine_path(row.path.relative_to(data_dir).as_posix())
    real_holds, quarantined = uploads.holds, []

    def holds_after_the_operator(path, sha256) -> bool:  # the CLI's call, on a connection of its own
        if not quarantined:
            quarantined.append(Catalog(data_dir).quarantine(row.episode_id, "operator: wrong object"))
        return real_holds(path, sha256)

    monkeypatch.setattr(uploads, "holds", holds_after_the_operator)

    assert upload(client, keys, grant, data) == {**body, "duplicate": True}

    assert quarantined and quarantined[0].quarantined == "operator: wrong object"
    after = catalog.get(row.episode_id)
    assert after.quarantined == "operator: wrong object", "the repeat ended the operator's quarantine"
    assert not row.path.exists() and kept.read_bytes() == data
    assert [p for p in catalog.episodes_dir.rglob("*") if p.is_file()] == []  # no staging file left either
    assert catalog.count() == 1 and catalog.snapshot().ids == []
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, done.attempts) == (RequestStatus.DONE, body["episode_id"], 0)
    assert not catalog.restore(row.episode_id).quarantined and row.path.read_bytes() == data  # nothing lost


@pytest.mark.parametrize("file", ["moved", "lost"])
def test_an_operators_quarantine_that_commits_while_a_racing_copy_is_stored_stands(service, client, keys, data_dir,
                                                                                   monkeypatch, file) -> None:
    """The worker sent its first upload twice before the first reply came back. The second copy has checked its
    lease (still leased) when the first commits, then `activecollect episodes quarantine` (another process)
    commits, then the second copy's ingest finds the episode indexed. It is acknowledged, and the quarantine
    stands: the file stays in quarantine/ (``moved``), or, when the stored file was lost before the quarantine
    (``lost``: nothing to move), the copy's bytes are kept there; nothing is put back into episodes/."""
    request, _ = service.queue.enqueue(new_request())
    grant = lease(client, keys)
    data = episode_bytes(grant)
    header = messages.UploadHeader.for_payload(data, request_id=grant.request_id, token=grant.token, worker_id="w1")
    first_copy = Incoming(keys.upload, data, protocol.encode({"v": 1, **header.to_dict()}))
    handler, first = service._uploads, {}
    real_decode = handler._decode

    def first_copy_then_the_operator(raw, hdr, req):  # the second copy, between its lease check and its ingest
        if not first:
            first["reply"] = {}  # (the first copy's own decode goes straight on)
            first["reply"] = protocol.parse_reply(handler.handle(first_copy))  # the first copy, all the way
            row = Catalog(data_dir).get(first["reply"]["episode_id"])
            if file == "lost":
                row.path.unlink()
            subprocess.run([sys.executable, "-m", "orchestrator", "episodes", "quarantine", row.episode_id,
                            "--reason", "operator: wrong object", "--data", str(data_dir)], check=True)
        return real_decode(raw, hdr, req)

    monkeypatch.setattr(handler, "_decode", first_copy_then_the_operator)

    body = upload(client, keys, grant, data)

    assert body == {**first["reply"], "duplicate": True} and "duplicate" not in first["reply"]
    catalog = Catalog(data_dir)
    row = catalog.get(body["episode_id"])
    kept = data_dir / quarantine_path(row.path.relative_to(data_dir).as_posix())
    assert row.quarantined == "operator: wrong object", "the worker's racing copy ended the operator's quarantine"
    assert kept.read_bytes() == data and not row.path.exists() and catalog.snapshot().ids == []
    assert [p for p in catalog.episodes_dir.rglob("*") if p.is_file()] == []  # no staging file left either
    done = service.queue.get(request.id)
    assert (done.status, done.episode_id, catalog.count()) == (RequestStatus.DONE, row.episode_id, 1)
    assert not catalog.restore(row.episode_id).quarantined and row.path.read_bytes() == data  # nothing lost
