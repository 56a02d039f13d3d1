"""The dashboard's answers over real HTTP: every one says ``X-Content-Type-Options: nosniff`` (a 404 echoes the
path it was asked for), and the space of ``DATA/quarantine/`` shows on the page's numbers and in ``/metrics``."""

from __future__ import annotations

import socket
from urllib.parse import urlsplit

import pytest

from storage.catalog import Catalog
from tests.orchestrator.test_dashboard import _raw_http, read_to_close, serving


def head_lines(raw: bytes) -> list[bytes]:
    return raw.split(b"\r\n\r\n")[0].split(b"\r\n")


@pytest.mark.parametrize("raw, status", [
    (b"GET /api/stats HTTP/1.0\r\n\r\n", b"200"),
    (b"GET /<script>alert(1)</script> HTTP/1.0\r\n\r\n", b"404"),
    (b"POST /api/stats HTTP/1.0\r\n\r\n", b"405"),
    (b"GET / / HTTP/1.0\r\n\r\n", b"400"),  # the base class's own error page
    (b"HEAD /metrics HTTP/1.0\r\n\r\n", b"200"),
])
def test_every_answer_tells_the_browser_not_to_sniff_its_type(tmp_path, raw, status) -> None:
    Catalog(tmp_path)
    with serving(tmp_path) as dash, _raw_http(dash.url, raw) as conn:
        head = head_lines(read_to_close(conn))
    assert head[0].split(b" ")[1] == status, head
    assert b"X-Content-Type-Options: nosniff" in head, head
    if status in (b"404", b"405"):  # ours (the 404 repeats the path it was given: as HTML it would run that script;
        # the 400 is http.server's page, which escapes what it repeats)
        assert b"Content-Type: text/plain; charset=utf-8" in head, head


def test_the_503_of_a_full_dashboard_tells_the_browser_not_to_sniff_its_type(tmp_path) -> None:
    Catalog(tmp_path)
    with serving(tmp_path, max_connections=1, request_timeout_s=60) as dash:
        address = urlsplit(dash.url).hostname, urlsplit(dash.url).port
        with socket.create_connection(address, timeout=10), socket.create_connection(address, timeout=10) as extra:
            head = head_lines(read_to_close(extra))
    assert head[0] == b"HTTP/1.0 503 Service Unavailable" and b"X-Content-Type-Options: nosniff" in head, head
