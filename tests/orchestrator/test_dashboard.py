"""The dashboard: JSON endpoints, Prometheus text, and the page in a real headless Chromium.

The browser (``tests/orchestrator/browser.py``) is Debian's ``chromium``, installed here when missing
(root + apt), and driven over the DevTools protocol with ``websocket-client``.
"""

from __future__ import annotations

import contextlib
import gc
import http.client
import json
import os
import re
import select
import signal
import shutil
import socket
import struct
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Iterator
from urllib.parse import urlsplit

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from orchestrator.cli import build_parser
from orchestrator.companions import CompanionConfig
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.metrics import ServiceMetrics
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from storage.catalog import Catalog
from storage.database import quarantine_bytes
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from tests.conftest import run_cli, wait_for
from tests.orchestrator.browser import Browser, chromium_path
from tests.storage.test_episodes import make_episode




def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read()


@pytest.fixture
def stores(tmp_path):
    catalog = Catalog(tmp_path)
    queue = RequestQueue(catalog.db_path)
    registry = ModelRegistry(tmp_path)
    yield tmp_path, catalog, queue, registry
    queue.close()


@pytest.fixture
def dashboard(stores):
    data_dir, catalog, queue, registry = stores
    metrics = ServiceMetrics()
    def render() -> str:
        metrics.set_queue_depth(queue.counts())
        return metrics.render()
    src = DataSources(data_dir, workers=lambda: [{"id": "w1", "info": {"shapes": ["T"]}}],
                      metrics_text=render, budget=40, gauges=ServiceMetrics(quarantine_walk_s=0))
    dash = Dashboard(DashboardConfig(port=0, refresh_s=0.2), src.sources())
    dash.start()
    yield dash, queue, registry
    dash.stop()


def enqueue_uniform(queue: RequestQueue, n: int, seed: int = 0) -> None:
    for req in UniformPlanner(UniformPlannerConfig(), np.random.default_rng(seed)).seed(n):
        queue.enqueue(req)


def _raw_http(url: str, request: bytes) -> socket.socket:
    host, port = urlsplit(url).hostname, urlsplit(url).port
    conn = socket.create_connection((host, port), timeout=30)
    conn.sendall(request)
    return conn


def test_a_request_line_that_is_not_a_url_gets_400(dashboard):
    dash, _, _ = dashboard
    with _raw_http(dash.url, b"GET http://[x/ HTTP/1.0\r\n\r\n") as conn:
        assert conn.recv(4096).startswith(b"HTTP/1.0 400")


@pytest.mark.parametrize("line, status", [(b"GET / HTTP/2.0", b"505"), (b"GET / HTTP/x", b"400")])
def test_a_request_line_with_a_bad_version_gets_a_status_line_and_headers(dashboard, line, status):
    """The base class answered these HTTP/0.9-style: a bare HTML body, no status line, no nosniff header."""
    dash, _, _ = dashboard
    with _raw_http(dash.url, line + b"\r\n\r\n") as conn:
        reply = read_to_close(conn)
    assert reply.startswith(b"HTTP/1.0 " + status) and b"X-Content-Type-Options: nosniff" in reply, reply[:200]


def test_a_stalled_client_is_let_go(stores):
    data_dir = stores[0]
    dash = Dashboard(DashboardConfig(port=0, request_timeout_s=0.3), DataSources(data_dir).sources())
    dash.start()
    try:
        with _raw_http(dash.url, b"GET /api/stats HTTP/1.1\r\n") as conn:  # the headers never end
            assert conn.recv(4096) == b""  # closed by the server, not held until this client gives up
    finally:
        dash.stop()


@contextlib.contextmanager
def serving(data_dir: Path, **cfg) -> Iterator[Dashboard]:
    """A dashboard over ``data_dir`` on a free port, with ``cfg`` for its DashboardConfig."""
    dash = Dashboard(DashboardConfig(port=0, **cfg), DataSources(data_dir).sources())
    dash.start()
    try:
        yield dash
    finally:
        dash.stop()


def request(url: str, method: str, path: str) -> tuple[int, http.client.HTTPMessage, bytes]:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        conn.request(method, path)
        r = conn.getresponse()
        return r.status, r.headers, r.read()
    finally:
        conn.close()


def status_or_none(url: str) -> int | None:
    """The status of a GET, or None when the connection is refused or cut (as the server's 503 may be)."""
    try:
        return get(url)[0]
    except (OSError, http.client.HTTPException):
        return None


def read_to_close(conn: socket.socket) -> bytes:
    chunks = []
    while chunk := conn.recv(4096):
        chunks.append(chunk)
    return b"".join(chunks)


def test_a_client_trickling_its_request_is_let_go_at_the_deadline(stores):
    timeout = 0.5
    with serving(stores[0], request_timeout_s=timeout, max_connections=1) as dash:
        with _raw_http(dash.url, b"GET /api/stats HTTP/1.0\r\nX-Slow: ") as conn:
            give_up, closed = time.monotonic() + 10 * timeout, False
            while not closed and time.monotonic() < give_up:
                try:  # a byte every 50 ms: each read is quick, the request as a whole never ends
                    conn.sendall(b"x")
                    if select.select([conn], [], [], 0.05)[0]:  # paces the trickle and sees the server close
                        closed = conn.recv(4096) == b""
                except (ConnectionResetError, BrokenPipeError):
                    closed = True
            assert closed, f"the server still read the trickle {10 * timeout:g} s on (request_timeout_s={timeout:g})"
        # the connection's one slot came back
        wait_for(lambda: status_or_none(dash.url + "api/workers") == 200, message="a GET to be served again")


def test_connections_over_the_cap_get_503_and_the_cap_frees_as_they_close(stores):
    with serving(stores[0], max_connections=2, request_timeout_s=60) as dash:
        host, port = urlsplit(dash.url).hostname, urlsplit(dash.url).port
        idle = [socket.create_connection((host, port), timeout=10) for _ in range(2)]  # accepted first, in order
        try:
            with socket.create_connection((host, port), timeout=5) as extra:
                response = read_to_close(extra)  # at once: not after the 60 s the idle ones may take
            head = response.split(b"\r\n\r\n")[0].split(b"\r\n")
            assert head[0] == b"HTTP/1.0 503 Service Unavailable" and b"Retry-After: 1" in head
        finally:
            for conn in idle:
                conn.close()
        wait_for(lambda: status_or_none(dash.url + "api/workers") == 200, message="a GET once the idle ones closed")


def test_a_client_that_resets_mid_request_gives_its_slot_back(stores, capfd, caplog):
    caplog.set_level("DEBUG", logger="orchestrator.dashboard")
    with serving(stores[0], max_connections=1, request_timeout_s=60) as dash:
        vanishing = _raw_http(dash.url, b"GET /api/stats HTTP/1.0\r\nX-Partial: ")  # takes the one slot
        with socket.create_connection(vanishing.getpeername(), timeout=5) as extra:
            assert read_to_close(extra).startswith(b"HTTP/1.0 503 ")
        vanishing.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        vanishing.close()  # linger 0: a reset, so the handler's read raises rather than ends
        wait_for(lambda: status_or_none(dash.url + "api/workers") == 200, message="a GET after the reset")
    assert "Traceback" not in capfd.readouterr().err  # a client going away is no error of ours
    assert not [r for r in caplog.records if r.levelname == "ERROR"]
    assert any("went away" in r.getMessage() and r.levelname == "DEBUG" for r in caplog.records)


def test_a_failure_of_ours_is_logged_with_its_traceback_and_a_client_going_away_is_not(stores, caplog):
    with serving(stores[0]) as dash:
        server = dash._server
        for exc in (ConnectionResetError(104, "reset"), BrokenPipeError(32, "broken"), RuntimeError("a bug")):
            caplog.clear()
            with caplog.at_level("DEBUG", logger="orchestrator.dashboard"):
                try:
                    raise exc
                except Exception:
                    server.handle_error(None, ("127.0.0.1", 1))
            [record] = caplog.records
            if isinstance(exc, RuntimeError):
                assert record.levelname == "ERROR" and record.exc_info[1] is exc
            else:
                assert record.levelname == "DEBUG" and "went away" in record.getMessage() and not record.exc_info


def test_max_connections_must_be_positive():
    with pytest.raises(ValueError, match="max_connections"):
        DashboardConfig(max_connections=0)


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE"])
def test_methods_other_than_get_and_head_are_405_with_allow(dashboard, method):
    dash, _, _ = dashboard
    status, headers, body = request(dash.url, method, "/api/stats")
    assert status == 405 and headers["Allow"] == "GET, HEAD" and method.encode() in body


def test_head_gives_the_headers_of_get_without_a_body(dashboard):
    dash, _, _ = dashboard
    get_status, get_headers, get_body = request(dash.url, "GET", "/api/workers")
    head_status, head_headers, head_body = request(dash.url, "HEAD", "/api/workers")
    assert get_status == head_status == 200 and get_body and head_body == b""
    for name in ("Content-Type", "Content-Length", "Cache-Control"):
        assert head_headers[name] == get_headers[name]


@pytest.mark.parametrize("raw", [b"GET /api/workers HTTP/1.0\r\n\r\n", b"GET /nope HTTP/1.0\r\n\r\n",
                                 b"GET / / HTTP/1.0\r\n\r\n"])  # served, 404, and the base class's own 400
def test_the_server_header_names_no_versions(dashboard, raw):
    dash, _, _ = dashboard
    with _raw_http(dash.url, raw) as conn:
        head = read_to_close(conn).split(b"\r\n\r\n")[0].split(b"\r\n")
    assert b"Server: activecollect-dashboard" in head, head


def test_api_endpoints_answer_json(dashboard, tmp_path):
    dash, queue, registry = dashboard
    enqueue_uniform(queue, 3)
    version = registry.register(b"weights", {"image_size": 16}, {"h1_mse": 0.02, "h5_mse": 0.05},
                                snapshot_id="snap", eval_split_hash="hash")
    registry.promote(version)
    status, ctype, body = get(dash.url + "api/queue")
    assert status == 200 and ctype == "application/json"
    q = json.loads(body)
    assert q["counts"]["queued"] == 3 and len(q["requests"]) == 3
    assert q["requests"][0]["reason"]["planner"] == "seed"
    models = json.loads(get(dash.url + "api/models")[2])
    assert models["champion"] == version and models["models"][0]["metrics"]["h1_mse"] == 0.02
    stats = json.loads(get(dash.url + "api/stats")[2])
    assert stats["champion"] == version and stats["champion_h1_mse"] == 0.02 and stats["budget"] == 40
    assert stats["workers_alive"] == 1 and stats["disk"]["size_bytes"] == shutil.disk_usage(tmp_path).total
    # no retrain ran in this process (a restarted service, a dashboard of its own): the registry's newest model
    assert stats["retrains"] == 0 and stats["last_retrain"] == {
        "status": "champion", "version": version, "reason": registry.get(version).reason,
        "finished": registry.get(version).created, "from": "registry"}
    assert json.loads(get(dash.url + "api/workers")[2])["workers"][0]["id"] == "w1"
    [point] = json.loads(get(dash.url + "api/curve")[2])["points"]
    assert point["version"] == version and point["episodes"] == 0 and point["status"] == "champion"
    status, ctype, body = get(dash.url + "frames.png")
    assert status == 200 and ctype == "image/png" and body.startswith(b"\x89PNG")
    assert get(dash.url + "nope")[0] == 404


def test_metrics_parse_as_prometheus_text(dashboard):
    dash, queue, _ = dashboard
    enqueue_uniform(queue, 2)
    status, ctype, body = get(dash.url + "metrics")
    assert status == 200 and ctype.startswith("text/plain; version=0.0.4")
    families = {f.name: f for f in text_string_to_metric_families(body.decode())}
    depth = {s.labels["status"]: s.value for s in families["activecollect_queue_depth"].samples}
    assert depth["queued"] == 2.0 and depth["done"] == 0.0


def test_a_dashboard_without_a_service_reads_its_metrics_from_the_data_directory(stores):
    data_dir, catalog, queue, registry = stores
    enqueue_uniform(queue, 3)
    for _ in range(2):
        catalog.add_episode(make_episode(np.random.default_rng(len(catalog.list()))))
    catalog.quarantine(catalog.list()[1].episode_id, "found by a training job: missing")
    version = registry.register(b"weights", {}, {"h1_mse": 0.02}, snapshot_id="snap", eval_split_hash="hash")
    registry.promote(version)
    dash = Dashboard(DashboardConfig(port=0), DataSources(data_dir).sources())  # as `activecollect dashboard`
    dash.start()
    try:
        status, _, body = get(dash.url + "metrics")
        stats = json.loads(get(dash.url + "api/stats")[2])
    finally:
        dash.stop()
    assert stats["episodes"] == {"train": 2, "eval": 0, "quarantined": 1}
    families = {f.name: f for f in text_string_to_metric_families(body.decode())}
    depth = {s.labels["status"]: s.value for s in families["activecollect_queue_depth"].samples}
    assert status == 200 and depth["queued"] == 3.0
    assert families["activecollect_champion_h1_mse"].samples[0].value == 0.02
    assert families["activecollect_champion_info"].samples[0].labels["version"] == version
    size = families["activecollect_data_disk_size_bytes"].samples[0].value
    assert size == shutil.disk_usage(data_dir).total
    assert families["activecollect_data_disk_free_bytes"].samples[0].value > 0
    assert families["activecollect_episodes_quarantined"].samples[0].value == 1
    assert families["activecollect_champion_weights_damaged"].samples[0].value == 0
    registry.get(version).weights_path.write_bytes(b"damaged")
    dash = Dashboard(DashboardConfig(port=0), DataSources(data_dir).sources())
    dash.start()
    try:
        families = {f.name: f for f in text_string_to_metric_families(get(dash.url + "metrics")[2].decode())}
        stats = json.loads(get(dash.url + "api/stats")[2])
    finally:
        dash.stop()
    assert families["activecollect_champion_weights_damaged"].samples[0].value == 1
    assert "weights sha256 mismatch" in stats["champion_problem"]


def test_requests_give_their_database_files_back_when_they_finish(stores):
    """Each connection runs on a new thread: stores kept per thread held their SQLite files (the connections
    are in reference cycles) until the cyclic GC ran, ~400 fds after 10k requests. Off here, so it cannot."""
    data_dir, _, queue, _ = stores
    enqueue_uniform(queue, 2)
    gc.disable()
    try:
        with serving(data_dir) as dash:
            get(dash.url + "metrics")  # the first request's one-time costs (e.g. imports) before counting
            before = len(os.listdir("/proc/self/fd"))
            for i in range(60):
                status, _, _ = get(dash.url + ("api/stats", "api/queue", "metrics", "api/models", "api/curve")[i % 5])
                assert status == 200
            wait_for(lambda: len(os.listdir("/proc/self/fd")) <= before + 4,  # a socket not yet closed
                     message=f"the process's fds back to about {before}")
    finally:
        gc.enable()


# -- the real browser --------------------------------------------------------------------------

@pytest.fixture
def browser(tmp_path):
    binary = chromium_path()
    b = Browser(binary, tmp_path / "chromium-profile")
    yield b
    b.close()


@pytest.mark.timeout(1500)  # the first run on a fresh machine installs chromium
def test_page_shows_live_queue_numbers_without_console_errors(dashboard, stores, browser):
    dash, queue, registry = dashboard
    enqueue_uniform(queue, 2)
    browser.call("Runtime.enable")
    browser.call("Log.enable")
    browser.call("Page.enable")
    browser.call("Page.navigate", url=dash.url)
    queued = lambda: browser.evaluate("document.getElementById('q-queued').textContent")  # noqa: E731
    wait_for(lambda: queued() == "2", message="the page to show 2 queued requests")
    assert browser.evaluate("document.getElementById('workers-alive').textContent") == "1"
    assert browser.evaluate("document.querySelectorAll('#queue tbody tr').length") == 2
    # a request added behind the page's back shows up without a reload
    enqueue_uniform(queue, 1, seed=1)
    wait_for(lambda: queued() == "3", message="the page to show the new request")
    # a champion appears in the models table and the cards
    version = registry.register(b"weights", {}, {"h1_mse": 0.01, "h5_mse": 0.03},
                                snapshot_id="snap", eval_split_hash="hash")
    registry.promote(version)
    wait_for(lambda: browser.evaluate("document.getElementById('champion').textContent") == version,
             message="the champion card")
    assert browser.evaluate("document.getElementById('last-retrain').textContent") == "champion (newest model)"
    wait_for(lambda: browser.evaluate("document.querySelectorAll('#curve circle').length") == 1,
             message="the learning curve point")
    assert browser.evaluate("document.getElementById('updated').textContent").startswith("updated")
    # an operator's request whose reason holds odd types (any JSON object is allowed) still shows
    odd = UniformPlanner(UniformPlannerConfig(), np.random.default_rng(2)).seed(1)[0]
    odd.reason = {"source_episode": 7, "score": "high", "step": [1]}
    queue.enqueue(odd)
    wait_for(lambda: browser.evaluate("document.querySelectorAll('#queue tbody tr').length") == 4,
             message="the queue table with the odd request")
    assert browser.evaluate("document.getElementById('updated').textContent").startswith("updated")
    assert browser.evaluate("document.getElementById('budget').textContent") == "of 40"
    # an episode taken out of training is counted beside the budget
    catalog = stores[1]
    catalog.add_episode(make_episode(np.random.default_rng(3)))
    catalog.quarantine(catalog.list()[0].episode_id, "operator: wrong object")
    held = f"of 40 \u00b7 1 quarantined ({quarantine_bytes(catalog.data_dir) / 1e3:.1f} kB)"  # and their files' space
    assert quarantine_bytes(catalog.data_dir) < 1e6  # (it showed "0.0 MB")
    wait_for(lambda: browser.evaluate("document.getElementById('budget').textContent") == held,
             message="the quarantined count")
    assert browser.errors() == []


@pytest.mark.parametrize("command", ["dashboard", "serve"])
def test_the_commands_pass_the_connection_cap_to_their_dashboard(command, spawn, spawn_service, data_dir):
    Catalog(data_dir)  # `dashboard` serves an existing data directory
    if command == "dashboard":
        proc = spawn("dashboard", "dashboard", "--data", str(data_dir), "--port", "0", "--max-connections", "1",
                     "--request-timeout", "60")
    else:
        proc = spawn_service("--dashboard-port", "0", "--dashboard-max-connections", "1",
                             "--dashboard-request-timeout", "60")
    found = wait_for(lambda: re.search(r"dashboard (?:on|at) (http://\S+)", proc.log()), timeout=60,
                     message=f"{command} to print its dashboard's address")
    url = urlsplit(found.group(1))
    with socket.create_connection((url.hostname, url.port), timeout=10):  # takes the one slot, idle
        with socket.create_connection((url.hostname, url.port), timeout=10) as extra:
            assert read_to_close(extra).startswith(b"HTTP/1.0 503 ")  # at once, not after the 60 s timeout
    wait_for(lambda: status_or_none(found.group(1) + "api/workers") == 200, message="a GET once the slot is free")


@pytest.mark.parametrize("command", ["dashboard", "serve"])
def test_the_commands_pass_the_request_timeout_to_their_dashboard(command, spawn, spawn_service, data_dir):
    Catalog(data_dir)
    if command == "dashboard":
        proc = spawn("dashboard", "dashboard", "--data", str(data_dir), "--port", "0", "--request-timeout", "0.5")
    else:
        proc = spawn_service("--dashboard-port", "0", "--dashboard-request-timeout", "0.5")
    found = wait_for(lambda: re.search(r"dashboard (?:on|at) (http://\S+)", proc.log()), timeout=60,
                     message=f"{command} to print its dashboard's address")
    url = urlsplit(found.group(1))
    with socket.create_connection((url.hostname, url.port), timeout=10) as idle:  # sends nothing
        # let go after 0.5 s: well before the 5 s this waits, and the default of 10 s
        assert select.select([idle], [], [], 5.0)[0] and idle.recv(4096) == b""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_the_dashboard_command_stops_cleanly_on_sigterm_as_on_ctrl_c(spawn, data_dir, sig):
    """A supervisor's SIGTERM is a stop asked for, as for serve: exit 0, not 143."""
    Catalog(data_dir)
    proc = spawn("dashboard", "dashboard", "--data", str(data_dir), "--port", "0")
    wait_for(lambda: "dashboard on http" in proc.log(), timeout=60, message="the dashboard to start")
    proc.signal(sig)
    assert proc.wait(30) == 0, proc.log()


def test_dashboard_limits_must_be_positive(capsys):
    for argv in (["dashboard", "--max-connections", "0"], ["serve", "--dashboard-request-timeout", "nan"]):
        rc, _, err = run_cli(capsys, *argv)
        assert rc == 2 and "expected a positive" in err
    for argv in (["dashboard", "--request-timeout", "1e10"], ["serve", "--dashboard-request-timeout", "86401"]):
        rc, _, err = run_cli(capsys, *argv)  # a socket refuses ~9e9 s: every request would fail
        assert rc == 2 and "at most 86400 seconds" in err
    with pytest.raises(ValueError, match="max_connections"):
        CompanionConfig(dashboard_max_connections=0)


def _refused_when_parsed(capsys, argv: list[str]) -> str:
    """The one line of stderr with which the parser refuses ``argv``, exit 2."""
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("argv", [["dashboard", "--request-timeout", "1e-300"],
                                  ["serve", "--dashboard-request-timeout", "0.05"]])
def test_a_request_timeout_too_short_for_any_request_is_refused(capsys, argv):
    """``--request-timeout 1e-300`` was taken, and every client dropped (parsed only: the old code served)."""
    err = _refused_when_parsed(capsys, argv)
    assert f"expected at least 0.1 seconds (shorter drops clients before their request arrives), found '{argv[-1]}'" \
        in err
    with pytest.raises(ValueError, match=r"request_timeout_s must be in \[0.1, 86400\], found 1e-300"):
        DashboardConfig(request_timeout_s=1e-300)
    assert DashboardConfig(request_timeout_s=0.1).request_timeout_s == 0.1


@pytest.mark.parametrize("argv", [["dashboard", "--max-connections", "100000000000000000000"],
                                  ["serve", "--dashboard-max-connections", "4097"]])
def test_more_connections_than_threads_can_serve_are_refused(capsys, argv):
    """``--max-connections 10**20`` was taken: no cap at all, a thread per client until the system refused one."""
    err = _refused_when_parsed(capsys, argv)
    assert f"expected at most 4096 connections (a thread each), found {argv[-1]}" in err
    assert build_parser().parse_args(["dashboard", "--max-connections", "4096"]).max_connections == 4096
