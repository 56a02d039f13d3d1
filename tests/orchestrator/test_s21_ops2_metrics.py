"""``refusals_total`` tells the workers' refusals from an operator's (an admin query's typo) by a ``source`` label
of two values: an alert on ``source="worker"`` does not fire on operator typos, and a query by name and reason
alone still counts them all."""

from __future__ import annotations

import pytest
from prometheus_client.parser import text_string_to_metric_families

from orchestrator.metrics import REFUSAL_SOURCES, ServiceMetrics


def test_refusals_are_counted_by_source_under_the_same_name() -> None:
    m = ServiceMetrics()
    m.refusal("unknown_request")  # a worker's renew of a request the service does not know
    m.refusal("unknown_request", source="operator")  # `queue show` with a mistyped id
    m.refusal("unknown_request", source="operator")
    m.refusal("bad_field", source="operator")
    samples = [s for f in text_string_to_metric_families(m.render()) if f.name == "activecollect_refusals"
               for s in f.samples if s.name == "activecollect_refusals_total"]
    by = {(s.labels["reason"], s.labels["source"]): s.value for s in samples}
    assert by == {("unknown_request", "worker"): 1, ("unknown_request", "operator"): 2, ("bad_field", "operator"): 1}
    get = m.registry.get_sample_value
    assert get("activecollect_refusals_total", {"reason": "unknown_request", "source": "worker"}) == 1
    # what a query by the series' name and reason alone (as before the label) adds up to
    assert sum(v for (reason, _), v in by.items() if reason == "unknown_request") == 3
    assert REFUSAL_SOURCES == ("worker", "operator")
    with pytest.raises(ValueError, match="refusal source must be one of worker, operator, found 'admin'"):
        m.refusal("bad_field", source="admin")  # a fixed set of values: no label an input can grow
