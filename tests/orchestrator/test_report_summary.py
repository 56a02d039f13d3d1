"""The run report's summary.json is strict JSON even when a candidate's eval error is NaN."""

from __future__ import annotations

import json

import pytest

from orchestrator.dashboard import learning_curve
from orchestrator.report import ReportInputs, write_report
from storage.catalog import Catalog
from storage.models import ModelRegistry


def _strict(text: str) -> object:
    def refuse(constant: str) -> None:
        raise ValueError(f"not strict JSON: {constant}")
    return json.loads(text, parse_constant=refuse)


def test_a_diverged_candidate_leaves_summary_json_strict(tmp_path) -> None:
    """A training run that diverged registers NaN metrics and the gate rejects it; the report's curve keeps its
    point, and summary.json held a bare NaN that browsers and jq refuse."""
    catalog, registry = Catalog(tmp_path), ModelRegistry(tmp_path)
    good = registry.register(b"w1", {}, {"h1_mse": 0.02, "train_episodes": 4}, snapshot_id="s1",
                             eval_split_hash="h")
    registry.promote(good)
    bad = registry.register(b"w2", {}, {"h1_mse": float("nan"), "train_episodes": 8}, snapshot_id="s2",
                            eval_split_hash="h")
    assert not registry.gate(bad).promoted
    retrain = {"trigger": "round", "episodes": 8, "status": "rejected", "version": bad,
               "metrics": {"h1_mse": float("inf")}, "started": 1.0, "finished": 2.0}
    index = write_report(tmp_path, ReportInputs(curve=learning_curve(catalog, registry), retrains=[retrain],
                                                summary={"champion": good, "champion_h1_mse": float("nan")}))
    summary = _strict((index.parent / "summary.json").read_text())
    points = {p["version"]: p for p in summary["curve"]}
    assert points[good]["h1_mse"] == pytest.approx(0.02) and points[bad]["h1_mse"] is None
    assert summary["retrains"][0]["metrics"]["h1_mse"] is None and summary["summary"]["champion_h1_mse"] is None
