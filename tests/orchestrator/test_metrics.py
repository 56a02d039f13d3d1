"""The service metrics render as Prometheus text that a Prometheus parser reads back."""

from __future__ import annotations

import math
import threading

import pytest
from prometheus_client.parser import text_string_to_metric_families

from orchestrator.metrics import CONTENT_TYPE, ServiceMetrics


def _samples(text: str) -> dict[tuple[str, tuple], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def test_render_parses_and_holds_what_was_recorded() -> None:
    m = ServiceMetrics()
    m.set_queue_depth({"queued": 3, "leased": 1})
    m.lease()
    m.lease(2)
    m.upload("stored")
    m.upload("stored")
    m.upload("duplicate")
    m.refusal("bad_sha256")
    m.refusal('we"ird\\label\nvalue')
    m.retrain("promoted")
    m.observe_scoring(0.02)
    m.observe_scoring(0.3)
    with m.time_scoring():
        pass
    m.set_workers_alive(2)
    m.set_episodes({"train": 10, "eval": 4})
    m.set_champion("m000001-abcdef12", 0.0123)

    text = m.render()
    assert "# HELP activecollect_queue_depth" in text and "# TYPE activecollect_leases_total counter" in text
    s = _samples(text)
    assert s[("activecollect_queue_depth", (("status", "queued"),))] == 3
    assert s[("activecollect_queue_depth", (("status", "dead"),))] == 0  # always exported
    assert s[("activecollect_leases_total", ())] == 3
    assert s[("activecollect_uploads_total", (("result", "stored"),))] == 2
    assert s[("activecollect_uploads_total", (("result", "refused"),))] == 0
    assert s[("activecollect_refusals_total", (("reason", "bad_sha256"), ("source", "worker")))] == 1
    assert s[("activecollect_refusals_total", (("reason", 'we"ird\\label\nvalue'), ("source", "worker")))] == 1
    assert s[("activecollect_retrains_total", (("outcome", "promoted"),))] == 1
    assert s[("activecollect_scoring_seconds_count", ())] == 3
    assert s[("activecollect_scoring_seconds_bucket", (("le", "0.025"),))] >= 1
    assert s[("activecollect_scoring_seconds_bucket", (("le", "+Inf"),))] == 3
    assert s[("activecollect_scoring_seconds_sum", ())] == pytest.approx(0.32, abs=0.05)
    assert s[("activecollect_workers_alive", ())] == 2
    assert s[("activecollect_episodes", (("split", "eval"),))] == 4
    assert s[("activecollect_champion_info", (("version", "m000001-abcdef12"),))] == 1
    assert s[("activecollect_champion_h1_mse", ())] == pytest.approx(0.0123)
    assert CONTENT_TYPE.startswith("text/plain") and "0.0.4" in CONTENT_TYPE


def test_queue_depth_and_champion_are_replaced_not_accumulated() -> None:
    m = ServiceMetrics()
    m.set_queue_depth({"queued": 5})
    m.set_queue_depth({"leased": 2})
    m.set_champion("m1", 0.5)
    m.set_champion(None)
    s = _samples(m.render())
    assert s[("activecollect_queue_depth", (("status", "queued"),))] == 0
    assert s[("activecollect_queue_depth", (("status", "leased"),))] == 2
    assert not any(name == "activecollect_champion_info" for name, _ in s)
    assert math.isnan(s[("activecollect_champion_h1_mse", ())])


def test_a_scrape_always_finds_the_champion_while_it_is_named_again() -> None:
    """The service names the champion on every reap; a scrape in between must not find no series (absent())."""
    m = ServiceMetrics()
    m.set_champion("m1", 0.1)
    stop = threading.Event()

    def reap() -> None:
        while not stop.is_set():
            m.set_champion("m1", 0.1)

    reaper = threading.Thread(target=reap)
    reaper.start()
    try:
        seen = [m.registry.get_sample_value("activecollect_champion_info", {"version": "m1"}) for _ in range(300)]
    finally:
        stop.set()
        reaper.join()
    assert seen.count(None) == 0, f"{seen.count(None)} of {len(seen)} scrapes found no champion_info"
    m.set_champion("m2", 0.05)  # a new champion replaces the old series
    s = _samples(m.render())
    assert [labels for name, labels in s if name == "activecollect_champion_info"] == [(("version", "m2"),)]


def test_no_champion_is_nan_not_a_perfect_zero() -> None:
    assert math.isnan(_samples(ServiceMetrics().render())[("activecollect_champion_h1_mse", ())])


def test_instances_do_not_share_state() -> None:
    a, b = ServiceMetrics(), ServiceMetrics()
    a.lease()
    assert _samples(b.render())[("activecollect_leases_total", ())] == 0


def test_unknown_labels_are_refused() -> None:
    m = ServiceMetrics()
    with pytest.raises(ValueError, match="upload result must be one of stored, duplicate, refused"):
        m.upload("maybe")
    with pytest.raises(ValueError, match="retrain outcome"):
        m.retrain("great")
    with pytest.raises(ValueError, match="non-empty"):
        m.refusal("")


def test_counting_from_threads_loses_nothing() -> None:
    m = ServiceMetrics()

    def work() -> None:
        for _ in range(500):
            m.lease()
            m.upload("stored")

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    s = _samples(m.render())
    assert s[("activecollect_leases_total", ())] == 2000
    assert s[("activecollect_uploads_total", (("result", "stored"),))] == 2000


def test_the_disk_gauges_say_unknown_until_read() -> None:
    m = ServiceMetrics()
    s = _samples(m.render())
    assert math.isnan(s[("activecollect_data_disk_free_bytes", ())])
    m.set_disk({"free_bytes": 5 << 30, "size_bytes": 20 << 30})
    s = _samples(m.render())
    assert s[("activecollect_data_disk_free_bytes", ())] == 5 << 30
    assert s[("activecollect_data_disk_size_bytes", ())] == 20 << 30


def test_a_retrain_that_found_the_lock_taken_is_busy_not_failed() -> None:
    """A cron retrain meeting a manual one did nothing wrong: an alert on failed retrains must not fire for it;
    a failure, a timeout and a kill do count as failed."""
    from orchestrator.metrics import retrain_outcome
    from orchestrator.retrainjob import RetrainStatus

    outcomes = {status.value: retrain_outcome(status.value) for status in RetrainStatus if status.value != "running"}
    assert outcomes == {"promoted": "promoted", "rejected": "rejected", "busy": "busy", "failed": "failed",
                        "killed": "failed", "timeout": "failed"}
    metrics = ServiceMetrics()
    metrics.retrain(retrain_outcome("busy"))
    assert 'activecollect_retrains_total{outcome="busy"} 1.0' in metrics.render()
    assert 'activecollect_retrains_total{outcome="failed"} 0.0' in metrics.render()
    # (its help names every outcome a series has: busy was missing)
    assert "# HELP activecollect_retrains_total Retrain jobs finished, by outcome (promoted, rejected, busy, " \
           "failed)." in metrics.render()
