"""A dashboard over a data directory that cannot be read: it says why in one line, warns once, makes nothing,
and shows no number it cannot know (live workers, without the service)."""

from __future__ import annotations

import http.client
import json
import logging
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from orchestrator.champion import ChampionScorer, FramesSource
from orchestrator.dashboard import RETRY_AFTER_S, Dashboard, DashboardConfig, DashboardSources, DataSources
from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from tests.conftest import wait_for
from tests.orchestrator.browser import Browser, chromium_path
from tests.orchestrator.test_dashboard import serving


def fetch(url: str, path: str) -> tuple[int, http.client.HTTPMessage, bytes]:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        conn.request("GET", path)
        r = conn.getresponse()
        return r.status, r.headers, r.read()
    finally:
        conn.close()


@pytest.fixture
def browser(tmp_path):
    b = Browser(chromium_path(), tmp_path / "chromium-profile")
    yield b
    b.close()


def test_a_data_directory_moved_away_is_not_made_again(tmp_path: Path) -> None:
    """Opening the stores of a directory with no catalog made a new, empty one (and its folders): the page showed
    an empty fleet, and the directory was back where the operator had just moved it from."""
    data_dir = tmp_path / "data"
    catalog = Catalog(data_dir)
    frames = FramesSource(ChampionScorer(data_dir), catalog)  # as `activecollect dashboard` has it
    dash = Dashboard(DashboardConfig(port=0), DataSources(data_dir, frames_png=frames).sources())
    dash.start()
    try:
        assert fetch(dash.url, "/api/stats")[0] == 200
        data_dir.rename(tmp_path / "moved")
        # /frames.png: the champion's loader opened the registry, which made the directory again
        for path in ("/api/stats", "/api/queue", "/api/models", "/api/curve", "/metrics", "/frames.png"):
            status, headers, body = fetch(dash.url, path)
            assert status == 500 and headers["Content-Type"].startswith("text/plain"), (path, status, body)
            assert body.decode().startswith(f"no catalog at {data_dir}:") and body.count(b"\n") == 1, body
    finally:
        dash.stop()
    assert not data_dir.exists()


def test_a_damaged_catalog_is_one_line_to_the_client_and_one_warning_not_a_traceback_each_time(
        tmp_path: Path, caplog) -> None:
    (tmp_path / "catalog.sqlite").write_bytes(b"not a database " * 100)
    caplog.set_level(logging.DEBUG, logger="orchestrator.dashboard")
    with serving(tmp_path) as dash:
        for _ in range(3):  # a page refreshing every few seconds
            status, _, body = fetch(dash.url, "/api/stats")
            assert status == 500 and b"file is not a database" in body and body.count(b"\n") == 1, body
    records = [r for r in caplog.records if r.name == "orchestrator.dashboard" and r.levelno >= logging.WARNING]
    assert not [r for r in records if r.exc_info], "a damaged file is no bug of ours: no traceback"
    [warning] = records
    assert warning.levelname == "WARNING" and "/api/stats" in warning.getMessage()
    assert "file is not a database" in warning.getMessage()


def test_a_data_directory_busy_for_now_is_503_with_retry_after(tmp_path: Path) -> None:
    """A locked or full database passes: 503 asks a scraper or the page to come back, where 500 said it was broken."""
    def busy() -> dict:
        raise CatalogUnavailableError(f"cannot open the database {tmp_path / 'catalog.sqlite'}: database is locked")
    sources = DashboardSources(stats=busy, queue=lambda rows: {}, workers=list, models=dict, curve=list)
    dash = Dashboard(DashboardConfig(port=0), sources)
    dash.start()
    try:
        status, headers, body = fetch(dash.url, "/api/stats")
    finally:
        dash.stop()
    assert status == 503 and headers["Retry-After"] == str(RETRY_AFTER_S)
    assert body.decode().endswith("database is locked\n") and body.count(b"\n") == 1


def test_a_dashboard_without_the_service_does_not_say_no_worker_is_alive(tmp_path: Path) -> None:
    """Without the service the dashboard knows no workers: 'workers alive 0' beside leased requests was wrong."""
    Catalog(tmp_path)
    with serving(tmp_path) as dash:  # as `activecollect dashboard`
        assert json.loads(fetch(dash.url, "/api/stats")[2])["workers_alive"] is None
    src = DataSources(tmp_path, workers=lambda: [{"id": "w1"}, {"id": "w2"}])  # as serve's and run's
    dash = Dashboard(DashboardConfig(port=0), src.sources())
    dash.start()
    try:
        assert json.loads(fetch(dash.url, "/api/stats")[2])["workers_alive"] == 2
    finally:
        dash.stop()


@pytest.mark.timeout(1500)  # the first run on a fresh machine installs chromium
def test_the_page_says_workers_are_unknown_and_why_a_refresh_failed(tmp_path: Path, browser) -> None:
    data_dir = tmp_path / "data"
    Catalog(data_dir)
    with serving(data_dir, refresh_s=0.2) as dash:
        browser.call("Runtime.enable")
        browser.call("Page.navigate", url=dash.url)
        # '' until the page is there: an evaluate just after navigate may still meet the blank one before it
        updated = lambda: browser.evaluate("document.getElementById('updated')?.textContent ?? ''")  # noqa: E731
        wait_for(lambda: updated().startswith("updated"), message="the page's first refresh")
        assert browser.evaluate("document.getElementById('workers-alive').textContent") == "-"
        assert "unknown" in browser.evaluate("document.getElementById('workers-note').textContent")
        data_dir.rename(tmp_path / "moved")
        wait_for(lambda: updated().startswith("refresh failed:") and "no catalog at" in updated(),
                 message="the page to say why it cannot refresh")
