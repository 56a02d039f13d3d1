"""A request line without a version (HTTP/0.9's ``GET /``) is answered at once, and its connection slot given back:
the base class went on to read headers such a client never sends, holding the slot until the request timeout."""

from __future__ import annotations

import socket
from urllib.parse import urlsplit

import pytest

from orchestrator.dashboard import MAX_REQUEST_TIMEOUT_S
from storage.catalog import Catalog
from tests.conftest import wait_for
from tests.orchestrator.test_dashboard import read_to_close, serving, status_or_none


@pytest.mark.parametrize("line", [b"GET /\r\n", b"GET /api/stats\n", b"HEAD /metrics\r\n"])
def test_a_request_line_without_a_version_is_answered_at_once_and_frees_its_slot(tmp_path, line):
    Catalog(tmp_path)
    # one slot, and a day to send a request in: only an answer at once frees the slot for the GET after it
    with serving(tmp_path, max_connections=1, request_timeout_s=MAX_REQUEST_TIMEOUT_S) as dash:
        url = urlsplit(dash.url)
        with socket.create_connection((url.hostname, url.port), timeout=30) as conn:
            conn.sendall(line)  # and nothing more: such a client then waits for the answer
            answer = read_to_close(conn)
        assert answer.startswith(b"HTTP/1.0 505 "), answer
        assert b"HTTP/0.9" in answer.partition(b"\r\n\r\n")[2]  # the body says why
        wait_for(lambda: status_or_none(dash.url + "api/workers") == 200, message="a GET once the slot is free")
