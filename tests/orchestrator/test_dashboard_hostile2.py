"""Hostile requests to the dashboard that it already answers right, kept so: every endpoint's HEAD, paths that
try to leave the served set (``..``, encoded, a query string on each endpoint), pipelined requests on one
connection, and a client that resets while a large answer is being written."""

from __future__ import annotations

import contextlib
import socket
import struct
from typing import Iterator
from urllib.parse import urlsplit

import pytest

from orchestrator.dashboard import Dashboard, DashboardConfig, DashboardSources, DataSources
from storage.catalog import Catalog
from tests.conftest import wait_for
from tests.orchestrator.test_dashboard import read_to_close

ENDPOINTS = ["/", "/index.html", "/api/stats", "/api/queue", "/api/workers", "/api/models", "/api/curve",
             "/frames.png", "/metrics"]


@contextlib.contextmanager
def serving(sources: DashboardSources) -> Iterator[tuple[str, int]]:
    dash = Dashboard(DashboardConfig(port=0), sources)
    dash.start()
    try:
        parts = urlsplit(dash.url)
        yield parts.hostname, parts.port
    finally:
        dash.stop()


@pytest.fixture(scope="module")
def address(tmp_path_factory) -> Iterator[tuple[str, int]]:
    data_dir = tmp_path_factory.mktemp("data")
    Catalog(data_dir)
    with serving(DataSources(data_dir).sources()) as addr:
        yield addr


def exchange(address: tuple[str, int], raw: bytes) -> tuple[list[bytes], bytes]:
    """The head lines and the body of the answer to ``raw``, read to the server's close."""
    with socket.create_connection(address, timeout=30) as conn:
        conn.sendall(raw)
        head, _, body = read_to_close(conn).partition(b"\r\n\r\n")
    return head.split(b"\r\n"), body


def header(head: list[bytes], name: bytes) -> bytes | None:
    return next((line.split(b":", 1)[1].strip() for line in head if line.lower().startswith(name.lower() + b":")),
                None)


@pytest.mark.parametrize("path", ENDPOINTS + ["/nope"])
def test_head_of_every_endpoint_has_gets_length_and_type_and_no_body(address, path):
    get_head, get_body = exchange(address, f"GET {path} HTTP/1.0\r\n\r\n".encode())
    head, body = exchange(address, f"HEAD {path} HTTP/1.0\r\n\r\n".encode())
    assert head[0] == get_head[0] and body == b"" and header(get_head, b"Content-Length") == b"%d" % len(get_body)
    if path not in ("/api/stats", "/metrics"):  # (these two show the disk's free bytes, which change between reads)
        assert header(head, b"Content-Length") == header(get_head, b"Content-Length")
    assert header(head, b"Content-Length").isdigit()
    assert header(head, b"Content-Type") == header(get_head, b"Content-Type")


@pytest.mark.parametrize("path", ["/../catalog.sqlite", "/%2e%2e/catalog.sqlite", "/api/../catalog.sqlite",
                                  "/..%2fcatalog.sqlite", "//catalog.sqlite", "/catalog.sqlite", "/episodes/",
                                  "\\..\\catalog.sqlite", "/api/stats%00", "*"])
def test_a_path_out_of_the_served_set_is_404_and_gives_no_file(address, path):
    head, body = exchange(address, f"GET {path} HTTP/1.0\r\n\r\n".encode())
    assert head[0] == b"HTTP/1.0 404 Not Found" and body.startswith(b"no such page: ") and b"SQLite" not in body


@pytest.mark.parametrize("path", ENDPOINTS)
@pytest.mark.parametrize("query", [b"limit=-1&limit=99999999999999999999&rows=abc", b"\xff\xfe%ff%00", b"a" * 60000])
def test_a_query_string_on_any_endpoint_changes_nothing(address, path, query):
    head, _ = exchange(address, b"GET " + path.encode() + b"?" + query + b" HTTP/1.0\r\n\r\n")
    assert head[0] == b"HTTP/1.0 200 OK", head


def test_pipelined_requests_get_the_first_answer_whole_and_a_close(address):
    head, body = exchange(address, b"GET /api/workers HTTP/1.1\r\nHost: x\r\n\r\n" * 50)
    assert head[0] == b"HTTP/1.0 200 OK" and body == b'{"workers": []}'


def test_a_client_resetting_mid_answer_is_no_error_and_leaves_no_traceback(capfd, caplog):
    caplog.set_level("DEBUG", logger="orchestrator.dashboard")
    big = "#" * (16 << 20)  # far past what the socket buffers hold: the server is still writing at the reset
    sources = DashboardSources(stats=dict, queue=lambda _: {}, workers=list, models=dict, curve=list,
                               metrics_text=lambda: big)
    with serving(sources) as addr:
        conn = socket.create_connection(addr, timeout=30)
        conn.sendall(b"GET /metrics HTTP/1.0\r\n\r\n")
        assert conn.recv(15) == b"HTTP/1.0 200 OK"
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        conn.close()  # linger 0: a reset
        wait_for(lambda: any("went away" in r.getMessage() for r in caplog.records), message="the reset to be seen")
        head, _ = exchange(addr, b"GET /api/workers HTTP/1.0\r\n\r\n")
        assert head[0] == b"HTTP/1.0 200 OK"
    assert not [r for r in caplog.records if r.levelname in ("ERROR", "WARNING")]
    assert "Traceback" not in capfd.readouterr().err
