"""A data directory whose database another process holds locked: the dashboard says so (503, Retry-After) in a
scraper's time, not after the stores' 30 s busy timeout (Prometheus's default scrape timeout is 10 s)."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from urllib.parse import urlsplit

import pytest

from orchestrator.dashboard import READ_BUSY_TIMEOUT_S, RETRY_AFTER_S, Dashboard, DashboardConfig, DataSources
from orchestrator.dashboard_reader import MAX_HEADER_BYTES
from storage import database
from storage.catalog import Catalog
from storage.queue import RequestQueue
from tests.conftest import wait_for

_LOCKER = """
import sqlite3, sys
c = sqlite3.connect(sys.argv[1], isolation_level=None)
c.execute("PRAGMA locking_mode = EXCLUSIVE")
c.execute("BEGIN EXCLUSIVE")
c.execute("CREATE TABLE IF NOT EXISTS locker_probe(x)")  # a write: the exclusive lock is taken, WAL or not
print("locked", flush=True)
sys.stdin.readline()
c.execute("ROLLBACK")
"""


def _get(url: str) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=60) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def _dashboard_and_locker(data_dir) -> tuple[Dashboard, subprocess.Popen]:
    """A started dashboard over a new catalog in ``data_dir``, and a process that locks its database (it prints
    "locked" once it holds the lock, and lets go at a line on its stdin)."""
    catalog = Catalog(data_dir)
    RequestQueue(catalog.db_path).close()
    dash = Dashboard(DashboardConfig(port=0), DataSources(data_dir).sources())
    dash.start()
    locker = subprocess.Popen([sys.executable, "-c", _LOCKER, str(catalog.db_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    return dash, locker


@pytest.mark.parametrize("path", ["/api/stats", "/api/queue", "/api/models", "/metrics"])
def test_a_database_locked_by_another_process_is_503_within_a_scrape_timeout(tmp_path, path) -> None:
    dash, locker = _dashboard_and_locker(tmp_path)
    try:
        assert locker.stdout.readline().strip() == "locked"
        start = time.monotonic()
        status, headers, body = _get(dash.url.rstrip("/") + path)
        took = time.monotonic() - start
        assert status == 503 and headers["Retry-After"] == str(RETRY_AFTER_S), (status, body)
        assert b"locked" in body
        # a page's few reads may each wait READ_BUSY_TIMEOUT_S; each waited 30 s before (a bound, not a figure:
        # generous for a loaded machine, and still short of one old wait)
        assert took < min(READ_BUSY_TIMEOUT_S * 10, 25), took
    finally:
        locker.communicate("\n", timeout=30)
    try:
        assert _get(dash.url.rstrip("/") + path)[0] == 200  # the lock gone, it reads again
    finally:
        dash.stop()


def test_the_short_busy_timeout_is_the_dashboards_alone(tmp_path) -> None:
    """The service's own reads and writes, in other threads, keep the stores' busy timeout."""
    with database.busy_timeout(0.5):
        conn = database.connect(Catalog(tmp_path).db_path)
        assert conn.execute("PRAGMA busy_timeout").fetchone()[0] == 500
        conn.close()
    conn = database.connect(tmp_path / database.DB_NAME)
    assert conn.execute("PRAGMA busy_timeout").fetchone()[0] == database.BUSY_TIMEOUT_MS
    conn.close()


def _send_all_then_read(url: str, data: bytes) -> bytes:
    u = urlsplit(url)
    with socket.create_connection((u.hostname, u.port), timeout=30) as s:
        try:
            s.sendall(data)
        except OSError:  # answered and closed before it all went: what was answered is still read below
            pass
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out


def test_a_request_with_megabytes_of_headers_is_431_and_an_ordinary_one_is_served(tmp_path) -> None:
    """The base class took 100 header lines of 64 KiB each: 6.4 MB held per connection, ~200-600 MB of the
    serving process (the service's, under serve) for 32 connections."""
    Catalog(tmp_path)
    dash = Dashboard(DashboardConfig(port=0), DataSources(tmp_path).sources())
    dash.start()
    try:
        huge = b"GET / HTTP/1.0\r\n" + b"".join(b"X%d: " % i + b"y" * 60000 + b"\r\n" for i in range(99)) + b"\r\n"
        assert _send_all_then_read(dash.url, huge).startswith(b"HTTP/1.0 431 ")
        fits = b"GET / HTTP/1.0\r\n" + b"X: " + b"y" * (MAX_HEADER_BYTES - 100) + b"\r\n\r\n"
        assert _send_all_then_read(dash.url, fits).startswith(b"HTTP/1.0 200 ")
        long_line = b"GET /" + b"a" * 70000 + b" HTTP/1.0\r\n\r\n"
        assert _send_all_then_read(dash.url, long_line).startswith(b"HTTP/1.0 414 ")
    finally:
        dash.stop()


def test_while_a_request_waits_on_the_lock_other_threads_keep_the_stores_busy_timeout(tmp_path) -> None:
    """The short wait is set per request thread (a ContextVar): while a dashboard request is waiting on a locked
    database, connections opened by the service's own threads, and by a thread started meanwhile, keep the
    stores' 30 s (a module-wide setting would give the service's writes 2 s then)."""
    dash, locker = _dashboard_and_locker(tmp_path)
    statuses: list[int] = []
    request = threading.Thread(target=lambda: statuses.append(_get(dash.url.rstrip("/") + "/api/stats")[0]))
    try:
        assert locker.stdout.readline().strip() == "locked"
        request.start()
        wait_for(lambda: any("process_request_thread" in t.name for t in threading.enumerate()),
                 message="the dashboard serving the request")
        seen: list[int] = []

        def busy_ms() -> None:
            conn = database.connect(tmp_path / "other.sqlite")
            seen.append(conn.execute("PRAGMA busy_timeout").fetchone()[0])
            conn.close()

        busy_ms()
        other = threading.Thread(target=busy_ms)
        other.start()
        other.join()
        request.join(timeout=60)
        assert statuses == [503] and seen == [database.BUSY_TIMEOUT_MS] * 2
    finally:
        locker.communicate("\n", timeout=30)
        dash.stop()
