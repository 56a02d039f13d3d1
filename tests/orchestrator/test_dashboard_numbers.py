"""The numbers a dashboard over a data directory shows are the data directory's: no counts it cannot know,
and learning-curve points placed by what the catalog held when each model was made."""

from __future__ import annotations

import json
import urllib.request

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.metrics import NAMESPACE, STORE_GAUGES, ServiceMetrics
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from tests.conftest import wait_for
from tests.orchestrator.browser import Browser, chromium_path
from tests.orchestrator.test_dashboard import enqueue_uniform
from tests.storage.test_episodes import make_episode


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.status == 200
        return r.read()


def _served(data_dir, path: str) -> bytes:
    """GET ``path`` of a dashboard over ``data_dir`` with no service behind it (``activecollect dashboard``)."""
    dash = Dashboard(DashboardConfig(port=0), DataSources(data_dir).sources())
    dash.start()
    try:
        return _get(dash.url + path)
    finally:
        dash.stop()


def test_a_dashboard_without_a_service_exports_no_counts_it_cannot_know(tmp_path) -> None:
    """It counts no leases or uploads and sees no workers: exported as 0, an alert on a stalled upload rate or on
    no live workers fired whatever the service was doing. Only the data directory's gauges are there."""
    catalog = Catalog(tmp_path)
    with RequestQueue(catalog.db_path) as queue:
        enqueue_uniform(queue, 2)
    families = {f.name: f for f in text_string_to_metric_families(_served(tmp_path, "metrics").decode())}
    gauges = {"queue_depth", "episodes", "episodes_quarantined", "quarantine_bytes", "champion_h1_mse",
              "champion_weights_damaged", "champion_info", "data_disk_free_bytes",
              "data_disk_size_bytes"}  # champion_info: none, no series
    assert set(families) <= {f"{NAMESPACE}_{name}" for name in gauges}, sorted(families)
    assert families[f"{NAMESPACE}_data_disk_free_bytes"].samples[0].value > 0
    depth = {s.labels["status"]: s.value for s in families[f"{NAMESPACE}_queue_depth"].samples}
    assert depth["queued"] == 2.0


def test_the_service_still_exports_every_metric() -> None:
    m = ServiceMetrics()
    m.set_champion("m000001-abcdef12", 0.01)
    m.set_episodes({"train": 3, "eval": 1})
    names = {f.name for f in text_string_to_metric_families(m.render())}
    assert {f"{NAMESPACE}_workers_alive", f"{NAMESPACE}_leases", f"{NAMESPACE}_uploads"} <= names
    stores = {f.name for f in text_string_to_metric_families(m.render_stores())}
    assert stores == {f"{NAMESPACE}_{name}" for name in STORE_GAUGES} and stores < names


def test_a_curve_point_without_a_training_count_counts_what_the_catalog_held_when_the_model_was_made(
        tmp_path) -> None:
    """Episodes collected before the model (by their own clock) but ingested after it were no part of it."""
    catalog, registry = Catalog(tmp_path), ModelRegistry(tmp_path)
    catalog.add_episode(make_episode(np.random.default_rng(0)))
    version = registry.register(b"weights", {}, {"h1_mse": 0.02}, snapshot_id="snap", eval_split_hash="hash")
    for seed in (1, 2):  # collected elsewhere days earlier (make_episode's `created`), ingested now
        catalog.add_episode(make_episode(np.random.default_rng(seed)))
    [point] = json.loads(_served(tmp_path, "api/curve"))["points"]
    assert point["version"] == version
    assert point["episodes"] == 1


@pytest.fixture
def browser(tmp_path):
    b = Browser(chromium_path(), tmp_path / "chromium-profile")
    yield b
    b.close()


@pytest.mark.timeout(1500)  # the first run on a fresh machine installs chromium
def test_the_page_learning_curve_joins_the_champions_only(tmp_path, browser) -> None:
    """A rejected candidate is a grey dot beside the curve; the line through it drew a learning curve that had
    got worse when the champion had not."""
    registry = ModelRegistry(tmp_path)
    for h1, episodes in ((0.05, 10), (0.5, 20), (0.02, 30)):
        version = registry.register(b"weights %d" % episodes, {}, {"h1_mse": h1, "train_episodes": episodes},
                                    snapshot_id=f"snap{episodes}", eval_split_hash="hash")
        registry.gate(version)
    assert [m.status.value for m in registry.list()] == ["retired", "rejected", "champion"]
    dash = Dashboard(DashboardConfig(port=0, refresh_s=0.2), DataSources(tmp_path).sources())
    dash.start()
    try:
        browser.call("Runtime.enable")
        browser.call("Page.navigate", url=dash.url)
        wait_for(lambda: browser.evaluate("document.querySelectorAll('#curve circle').length") == 3,
                 message="the three models' points")
        circles = browser.evaluate("[...document.querySelectorAll('#curve circle')].map(c => "
                                   "[c.getAttribute('cx') + ',' + c.getAttribute('cy'), c.getAttribute('fill')])")
        line = browser.evaluate("document.querySelector('#curve polyline').getAttribute('points')")
    finally:
        dash.stop()
    assert [fill for _, fill in circles] == ["#1565c0", "#bbb", "#2e7d32"]  # retired, rejected, champion
    assert line.split() == [circles[0][0], circles[2][0]]
    assert browser.errors() == []
