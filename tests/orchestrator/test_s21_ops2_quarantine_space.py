"""The space the files of quarantined episodes take in ``DATA/quarantine/``, where an operator looks: the gauge
``activecollect_quarantine_bytes`` beside ``episodes_quarantined``, ``stats`` (admin and CLI) and the dashboard's
numbers. The walk is kept a while, not repeated for every request or every reap."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from prometheus_client.parser import text_string_to_metric_families

import orchestrator.metrics
from orchestrator import admin
from orchestrator.cli import main
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.metrics import QuarantineSpace, ServiceMetrics
from storage.catalog import Catalog
from storage.database import QUARANTINE_DIR, quarantine_bytes
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from tests.conftest import wait_for
from tests.orchestrator.test_dashboard import get
from tests.storage.test_episodes import make_episode


def quarantine_one(catalog: Catalog, seed: int) -> int:
    """Ingest an episode and quarantine it; the size of its file, now in DATA/quarantine/."""
    episode_id = catalog.add_episode(make_episode(np.random.default_rng(seed))).episode_id
    catalog.quarantine(episode_id, "operator: wrong object")
    kept = catalog.kept_file(catalog.get(episode_id))
    assert kept is not None and kept.is_relative_to(catalog.data_dir / QUARANTINE_DIR)
    return kept.stat().st_size


def gauge(text: str, name: str = "activecollect_quarantine_bytes") -> float:
    return {f.name: f for f in text_string_to_metric_families(text)}[name].samples[0].value


def test_quarantine_bytes_sums_the_files_kept_there(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    assert quarantine_bytes(tmp_path) == 0 and not (tmp_path / QUARANTINE_DIR).exists()
    sizes = [quarantine_one(catalog, seed) for seed in range(2)]
    assert sizes[0] > 0 and quarantine_bytes(tmp_path) == sum(sizes)
    catalog.restore(catalog.list(quarantined=True)[0].episode_id)
    assert quarantine_bytes(tmp_path) in sizes  # the restored one's file went back


def test_the_gauge_is_read_with_the_stores_and_walked_again_only_once_its_time_passes(tmp_path: Path) -> None:
    catalog, registry = Catalog(tmp_path), ModelRegistry(tmp_path)
    metrics = ServiceMetrics(quarantine_walk_s=3600.0)
    assert math.isnan(gauge(metrics.render()))  # unknown until the stores are read
    first = quarantine_one(catalog, 0)
    with RequestQueue(catalog.db_path) as queue:
        metrics.read_stores(queue, catalog, registry)
        assert gauge(metrics.render()) == first and gauge(metrics.render_stores()) == first
        quarantine_one(catalog, 1)
        metrics.read_stores(queue, catalog, registry)  # as the reaper does every second
        assert gauge(metrics.render()) == first  # not walked again within the hour
    space = QuarantineSpace(every_s=0.2)
    both = space.read(tmp_path)
    assert both == quarantine_bytes(tmp_path) > first
    catalog.restore(catalog.list(quarantined=True)[0].episode_id)
    assert 0 < quarantine_bytes(tmp_path) < both
    wait_for(lambda: space.read(tmp_path) == quarantine_bytes(tmp_path), message="the walk after every_s")


def test_admin_stats_say_the_space_of_the_quarantine(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path)
    with RequestQueue(catalog.db_path) as queue:
        assert admin.handle("stats", queue=queue, catalog=catalog)["quarantine_bytes"] == 0
        size = quarantine_one(catalog, 0)
        assert admin.handle("stats", queue=queue, catalog=catalog)["quarantine_bytes"] == size
        assert admin.handle("stats", queue=queue)["quarantine_bytes"] is None  # no catalog: unknown


def test_the_dashboard_shows_it_and_walks_once_for_many_requests(tmp_path: Path, monkeypatch) -> None:
    catalog = Catalog(tmp_path)
    size = quarantine_one(catalog, 0)
    walks: list[Path] = []
    real = orchestrator.metrics.quarantine_bytes

    def counted(data_dir):
        walks.append(Path(data_dir))
        return real(data_dir)

    monkeypatch.setattr(orchestrator.metrics, "quarantine_bytes", counted)
    dash = Dashboard(DashboardConfig(port=0), DataSources(tmp_path).sources())  # as `activecollect dashboard`
    dash.start()
    try:
        for _ in range(3):
            status, _, body = get(dash.url + "metrics")
            assert status == 200 and gauge(body.decode()) == size
            stats = json.loads(get(dash.url + "api/stats")[2])
            assert stats["quarantine_bytes"] == size and stats["episodes"]["quarantined"] == 1
    finally:
        dash.stop()
    assert walks == [tmp_path]  # six requests, one walk


def test_the_stats_command_says_the_space_of_the_quarantine(service, data_dir, endpoint, namespace, capsys) -> None:
    size = quarantine_one(Catalog(data_dir), 0)
    registry = ModelRegistry(data_dir)  # and the champion's h1 MSE beside its version
    champion = registry.register(b"weights" * 10, {}, {"h1_mse": 0.0123456}, snapshot_id="s", eval_split_hash="h")
    registry.promote(champion)
    argv = ["stats", "--connect", endpoint, "--namespace", namespace, "--timeout", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"quarantined=1 (their files take {size / 1e6:.1f} MB in DATA/quarantine/)" in out, out
    assert f"champion: {champion} (h1 MSE 0.0123)\n" in out, out
    assert main([*argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["quarantine_bytes"] == size
