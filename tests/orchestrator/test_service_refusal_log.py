"""A client refused again and again gets one log line a minute per (key, code, worker), the later ones with a count
of those not logged (``orchestrator.refusallog``); ``refusals_total`` counts every refusal. A real service (with a
fake elapsed clock) and a real Zenoh client over loopback."""

from __future__ import annotations

import logging
import time

from orchestrator import messages, refusallog, uploads
from orchestrator.protocol import ErrorCode, ProtocolError
from orchestrator.refusallog import RefusalLog, claimed_worker
from orchestrator.transport import Incoming
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

    jumped[0] = 61.0  # a window later
    refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w1")
    refused(ErrorCode.UNKNOWN_REQUEST, renew, client, keys, "w1")
    later = lines(caplog)[3:]
    assert len(later) == 1, later
    assert later[0].startswith(f"refused {keys.renew} from worker w1: unknown_request: "), later
    assert later[0].endswith("(and 19 more like it in the 61 s since the last such line)"), later
    counted = service.metrics.registry.get_sample_value(
        "activecollect_refusals_total", {"reason": "unknown_request", "source": "worker"})
    assert counted == 23  # every one


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
