"""A client refused again and again gets one log line a minute per (key, code, worker), the later ones with a count
of those not logged (``orchestrator.refusallog``); ``refusals_total`` counts every refusal. A real service (with a
fake elapsed clock) and a real Zenoh client over loopback."""

from __future__ import annotations

import logging
import re
import time

from orchestrator import messages, refusallog, uploads
from orchestrator.protocol import ErrorCode, ProtocolError
from orchestrator.refusallog import RefusalLog, claimed_worker
from orchestrator.transport import Incoming
from tests.conftest import wait_for
from tests.orchestrator.test_service import call, refused

UNKNOWN = "0123456789abcdef0123456789abcdef"


def renew(client, keys, worker: str) -> dict:
    """A renewal of a request the service never queued: refused ``unknown_request``."""
    return call(client, keys.renew, messages.RenewRequest(request_id=UNKNOWN, token=1, worker_id=worker).to_json())


def lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "orchestrator.service"
            and r.getMessage().startswith("refused ")]


def test_a_client_refused_again_and_again_gets_one_line_a_minute_with_a_count(make_service, client, keys,
                                                                              caplog) -> None:
    """It wrote one line per refusal: ~170,000 a day for a client asking twice a second."""
    jumped = [0.0]
    service = make_service(elapsed=lambda: time.monotonic() + jumped[0])
    caplog.set_level(logging.INFO, logger="orchestrator.service")
    for _ in range(20):
        refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w1")
    assert lines(caplog) == [f"refused {keys.renew} from worker w1: unknown_request: expected a known request id, "
                             f"found '{UNKNOWN}'"], lines(caplog)
    refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w2")  # another worker: a line of its own
    refused(ErrorCode.BAD_JSON, call, client, keys.renew, b"{")  # another code (and no worker): one too
    assert len(lines(caplog)) == 3, lines(caplog)

    jumped[0] = 61.0  # a window later: the reaper says the count it held (it was said only at a later refusal)
    wait_for(lambda: len(lines(caplog)) > 3, message="the reaper's line with the count")
    refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w1")  # counted afresh: no line
    refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w1")
    service.stop()  # says what it counted since
    later = lines(caplog)[3:]
    pattern = (rf"refused {re.escape(keys.renew)} from worker w1 (\d+) more time\(s\) in the (\d+) s since the last "
               rf"such line, the last: unknown_request: expected a known request id, found '{UNKNOWN}'")
    said = [re.fullmatch(pattern, line) for line in later]
    assert len(later) == 2 and all(said), later
    assert [int(m[1]) for m in said] == [19, 2] and 60 <= int(said[0][2]) <= 70, later
    counted = service.metrics.registry.get_sample_value(
        "activecollect_refusals_total", {"reason": "unknown_request", "source": "worker"})
    assert counted == 23  # every one


def test_a_later_refusal_says_the_count_and_a_flush_says_it_once_the_window_is_over() -> None:
    now = [0.0]
    records: list[str] = []
    log = logging.getLogger("test.refusallog.flush")
    log.addHandler(handler := logging.Handler())
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    log.setLevel(logging.INFO)
    refusals = RefusalLog(log, clock=lambda: now[0], window_s=60.0)
    exc = ProtocolError(ErrorCode.BAD_FIELD, "expected 64px")
    lease = Incoming("ns/orch/lease", messages.LeaseRequest(worker_id="old-1").to_json(), None)
    try:
        for _ in range(5):
            refusals.refused(lease, exc)
        refusals.flush()  # the window is not over: nothing
        assert records == ["refused ns/orch/lease from worker old-1: bad_field: expected 64px"]
        now[0] = 61.0
        refusals.refused(lease, exc)  # the window is over: a line with the count
        assert records[1:] == ["refused ns/orch/lease from worker old-1: bad_field: expected 64px (and 4 more like it "
                               "in the 61 s since the last such line)"]
        refusals.refused(lease, exc)
        now[0] = 130.0
        refusals.flush()
        refusals.flush()  # said once
        refusals.refused(lease, exc)  # within the flush's window: counted
        refusals.flush(everything=True)  # as the service stops
        assert records[2:] == [
            "refused ns/orch/lease from worker old-1 1 more time(s) in the 69 s since the last such line, the last: "
            "bad_field: expected 64px",
            "refused ns/orch/lease from worker old-1 1 more time(s) in the 0 s since the last such line, the last: "
            "bad_field: expected 64px"]
    finally:
        log.removeHandler(handler)


def test_the_kinds_it_keeps_are_bounded_by_its_own_cap(monkeypatch) -> None:
    """``KINDS_MAX`` bounds the refusal log, not the upload path's ``SIZELESS_MAX``; the oldest kind goes first."""
    monkeypatch.setattr(refusallog, "KINDS_MAX", 3)
    monkeypatch.setattr(uploads, "SIZELESS_MAX", 1)
    log = logging.getLogger("test.refusallog")
    refusals = RefusalLog(log, clock=lambda: 0.0)
    exc = ProtocolError(ErrorCode.BAD_FIELD, "x")
    for n in range(13):
        refusals.refused(Incoming(f"ns/orch/lease/{n}", b"", None), exc)
    assert [key for key, _, _ in refusals._kinds] == [f"ns/orch/lease/{n}" for n in (10, 11, 12)]


def test_the_worker_is_read_from_an_upload_header_or_the_body_and_only_a_valid_id() -> None:
    header = messages.UploadHeader.for_payload(b"mcap", request_id=UNKNOWN, token=1, worker_id="up-1")
    assert claimed_worker(Incoming("k", b"\x89MCAP", header.to_json())) == "up-1"
    lease = messages.LeaseRequest(worker_id="w.2").to_json()
    assert claimed_worker(Incoming("k", lease, None)) == "w.2"
    forged = b'{"v": 1, "worker_id": "w1\\nrefused everything"}'
    assert claimed_worker(Incoming("k", forged, None)) == ""
    assert claimed_worker(Incoming("k", b"[" * 3000, None)) == ""
    assert claimed_worker(Incoming("k", b'{"v": 1, "worker_id": "w1", "pad": "' + b"x" * 5000 + b'"}', None)) == ""
