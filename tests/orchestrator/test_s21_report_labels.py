"""The run report says what its numbers are: the curve's x axis, a resumed run's own episodes, an interrupted run,
a run without a champion; and it stays a page that needs no network and runs no text it was given."""

from __future__ import annotations

import re

from orchestrator.dashboard import learning_curve
from orchestrator.report import CURVE_X_LABEL, ReportInputs, curve_figure, write_report
from storage.catalog import Catalog
from storage.models import ModelRegistry


def test_the_learning_curve_is_labelled_by_the_episodes_each_model_was_trained_on(tmp_path) -> None:
    """Its x values are each model's train_episodes (what it trained on: quarantined episodes and those of another
    frame size left out); the axis and the heading said "training episodes collected"."""
    registry = ModelRegistry(tmp_path)
    registry.promote(registry.register(b"w", {}, {"h1_mse": 0.02, "train_episodes": 4}, snapshot_id="s",
                                       eval_split_hash="h"))
    curve = learning_curve(Catalog(tmp_path), registry)
    assert curve_figure(curve).axes[0].get_xlabel() == CURVE_X_LABEL == "training episodes the model was trained on"
    html = write_report(tmp_path, ReportInputs(curve=curve, summary={})).read_text()
    assert f"<h2>Eval error per {CURVE_X_LABEL}</h2>" in html and "collected" not in html


def test_an_interrupted_resumed_run_without_a_champion_says_so_escaped_and_offline(tmp_path) -> None:
    """Every retrain of a resumed run was rejected and it was stopped: the page says all three before its numbers,
    names the catalog's and this run's counts apart, escapes what a job wrote, and loads nothing from elsewhere."""
    retrain = {"trigger": "round", "episodes": 7, "status": "rejected", "version": "m<1>", "started": 1.0,
               "finished": 3.5, "metrics": {"h1_mse": 0.5}, "reason": "h1 <script>alert(1)</script> & worse"}
    summary = {"planner": "active", "episodes": 7, "collected_this_run": 3, "budget": 12, "retrains": 1,
               "champion": None, "champion_h1_mse": None, "interrupted": True, "seconds": 9.0}
    index = write_report(tmp_path, ReportInputs(curve=[], summary=summary, retrains=[retrain]))
    html = index.read_text()
    head = html.split("<table>")[0]
    assert "Interrupted (Ctrl-C or SIGTERM) before the budget was spent" in head
    assert "This run collected 3 of the catalog&#x27;s 7 training episodes" in head
    assert "No champion: no candidate has passed the promotion gate yet" in head
    assert "<th>training episodes (catalog)</th><td>7</td>" in html
    assert "<th>collected by this run</th><td>3</td>" in html and "<th>retrains (this run)</th><td>1</td>" in html
    assert "<script>" not in html and "h1 &lt;script&gt;alert(1)&lt;/script&gt; &amp; worse" in html
    assert "<td>m&lt;1&gt;</td>" in html
    assert not re.search(r"(?i)(https?:|//[a-z])", html)  # nothing fetched from a network
    sources = re.findall(r"src='([^']*)'", html)
    assert sources == ["curve.png"] and all((index.parent / s).is_file() for s in sources)


def test_a_fresh_finished_run_with_a_champion_has_no_headline(tmp_path) -> None:
    summary = {"episodes": 8, "collected_this_run": 8, "champion": "m000001-aa", "interrupted": False}
    html = write_report(tmp_path, ReportInputs(curve=[], summary=summary)).read_text()
    assert "<p>" not in html.split("<table>")[0]


def test_a_run_whose_every_retrain_was_rejected_says_its_champion_is_older(tmp_path) -> None:
    rejected = {"trigger": "round", "episodes": 8, "status": "rejected", "version": "m000002-bb", "started": 1.0,
                "finished": 2.0, "metrics": {"h1_mse": 0.03}, "reason": "not better"}
    summary = {"episodes": 8, "collected_this_run": 8, "champion": "m000001-aa", "interrupted": False}
    html = write_report(tmp_path, ReportInputs(curve=[], summary=summary, retrains=[rejected] * 2)).read_text()
    assert ("None of this run&#x27;s 2 retrains was promoted (see below): the champion, m000001-aa, is a model made "
            "before them.") in html.split("<table>")[0]
