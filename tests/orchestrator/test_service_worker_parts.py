"""A real worker process uploading an episode bigger than its ``--upload-part-kb`` in parts to an in-process
service: every part once, a retry going on from the part the service holds, from the start when the service
lost what it held, and whole to a service that takes no parts. (Over a slow link: tests/orchestrator/
test_partition.py.)"""

from __future__ import annotations

from orchestrator import messages
from storage.catalog import Catalog
from storage.requests import RequestStatus
from tests.orchestrator.test_service import new_request
from tests.orchestrator.test_service_upload_parts import full_disk_once

PART = 1024


def parts_seen(service, before_part=None) -> list[int]:
    """The offsets of the parts the service's staging is handed, in order; ``before_part(n, staging)`` runs
    before the n-th (from 0) is kept."""
    staging, offsets = service._uploads.parts, []
    real = staging.add

    def add(part, payload):
        offsets.append(part.offset)
        if before_part is not None:
            before_part(len(offsets) - 1, staging)
        return real(part, payload)

    staging.add = add
    return offsets


def upload_one(make_service, spawn_worker, data_dir, before_part=None, steps: int = 40):
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=steps))
    offsets = parts_seen(service, before_part)
    w = spawn_worker("P", "--once", "--upload-part-kb", str(PART // 1024))
    assert w.wait(60) == 0, w.log()
    done = service.queue.get(request.id)
    assert (done.status, done.attempts, done.token) == (RequestStatus.DONE, 0, 1), w.log()
    size = Catalog(data_dir).get(done.episode_id).size_bytes
    assert service._uploads.parts.held_bytes() == 0
    return offsets, list(range(0, size, PART)), w


def test_an_episode_bigger_than_a_part_is_uploaded_in_parts_each_once(make_service, spawn_worker, data_dir) -> None:
    offsets, every, _ = upload_one(make_service, spawn_worker, data_dir)
    assert len(every) >= 4 and offsets == every


def test_a_part_the_service_failed_on_is_sent_again_and_the_upload_goes_on_from_it(make_service, spawn_worker,
                                                                                   data_dir) -> None:
    def fail_third(n: int, staging) -> None:
        if n == 2:
            raise OSError(5, "Input/output error")  # answered `internal`: sent again after a backoff

    offsets, every, w = upload_one(make_service, spawn_worker, data_dir, fail_third)
    assert offsets == every[:3] + every[2:], w.log()  # not from the start
    assert "Input/output error; retrying" in w.log()


def test_parts_a_restarted_service_no_longer_holds_are_sent_again_from_the_start(make_service, spawn_worker,
                                                                                 data_dir) -> None:
    def forget_before_third(n: int, staging) -> None:  # what a restart does to the parts held in memory
        if n == 2:
            staging._held.clear()

    offsets, every, w = upload_one(make_service, spawn_worker, data_dir, forget_before_third)
    assert offsets == every[:3] + every, w.log()
    assert "the part at byte 2048 was not kept; the service holds 0 bytes" in w.log()


def test_a_service_that_takes_no_parts_gets_the_episodes_whole(make_service, spawn_worker, data_dir,
                                                               monkeypatch) -> None:
    """An older service refuses the part's header (an unknown field): the worker sends the episode whole, and
    its next episodes too, without trying parts again."""
    monkeypatch.setattr(messages, "upload_header", messages.UploadHeader.from_json)  # the older service's parse
    service = make_service()
    requests = [service.queue.enqueue(new_request(steps=40))[0] for _ in range(3)]
    w = spawn_worker("P", "--max-episodes", "3", "--upload-part-kb", "1")
    assert w.wait(60) == 0, w.log()
    assert all(service.queue.get(r.id).status == RequestStatus.DONE for r in requests), w.log()
    assert w.log().count("the service takes no upload in parts") == 1, w.log()


def test_a_last_part_the_service_could_not_store_for_now_is_the_only_part_sent_again(make_service, spawn_worker,
                                                                                    data_dir) -> None:
    """A full disk for a moment when the last part came: the service keeps the bytes, the worker sends that part
    again, not the whole episode."""
    service = make_service()
    request, _ = service.queue.enqueue(new_request(steps=40))
    offsets = parts_seen(service)
    failed = full_disk_once(service.catalog)
    w = spawn_worker("P", "--once", "--upload-part-kb", str(PART // 1024))
    assert w.wait(60) == 0, w.log()
    done = service.queue.get(request.id)
    every = list(range(0, Catalog(data_dir).get(done.episode_id).size_bytes, PART))
    assert failed and done.attempts == 0 and offsets == every + every[-1:], w.log()
