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


def test_a_rolled_back_model_is_not_on_the_champions_line(tmp_path) -> None:
    """Rollback retires the withdrawn model, and 'retired' counted as promoted: the line ended at it, in the report
    and on the dashboard, as if it were still the champion (a helper's reproduction)."""
    registry = ModelRegistry(tmp_path)
    first, second = (registry.register(b"w%d" % n, {}, {"h1_mse": h1, "train_episodes": n, "baseline_h1_mse": 0.06},
                                       snapshot_id=f"s{n}", eval_split_hash="h") for n, h1 in ((4, 0.05), (8, 0.02)))
    registry.gate(first)
    registry.gate(second)
    registry.rollback()
    points = {p["version"]: p for p in learning_curve(Catalog(tmp_path), registry)}
    assert (points[first]["promoted"], points[first]["rolled_back"], points[first]["status"]) == (True, False,
                                                                                                  "champion")
    assert (points[second]["promoted"], points[second]["rolled_back"]) == (False, True)
    labels = curve_figure(list(points.values())).axes[0].get_legend_handles_labels()[1]
    assert "h1_mse (rolled back)" in labels and "h1_mse (champion now)" in labels
    assert "h1_mse of copy-last-frame" in labels  # what a model must beat
    assert curve_figure(list(points.values())).axes[0].get_yscale() == "log"  # (h5 several times h1: h1 looked flat)
    static = [{**p, "h1_mse": 0.0} for p in points.values()]  # an error of 0 (frames that never change): linear
    assert curve_figure(static).axes[0].get_yscale() == "linear"


def test_a_run_whose_every_retrain_failed_and_one_whose_champion_cannot_be_loaded_say_so(tmp_path) -> None:
    failed = {"trigger": "round", "episodes": 8, "status": "failed", "version": None, "started": 1.0,
              "finished": 2.0, "metrics": {}, "reason": "training diverged"}
    summary = {"episodes": 8, "collected_this_run": 8, "champion": None, "interrupted": False}
    head = write_report(tmp_path / "a", ReportInputs(curve=[], summary=summary, retrains=[failed] * 2)
                        ).read_text().split("<table>")[0]
    assert "Every one of this run&#x27;s 2 retrains ended without a model (failed; see below)" in head
    assert "the disagreement map and the predicted-vs-real frames need one" in head
    timed_out = {**failed, "status": "timeout", "version": "m000002-bb", "reason": "timed out, after its gate had "
                 "rejected m000002-bb"}  # (killed after its gate: it made a model)
    head = write_report(tmp_path / "c", ReportInputs(curve=[], summary=summary, retrains=[timed_out])
                        ).read_text().split("<table>")[0]
    assert "ended without a model" not in head
    summary = {**summary, "champion": "m000001-aa", "champion_problem": "weights do not match their sha256"}
    head = write_report(tmp_path / "b", ReportInputs(curve=[], summary=summary)).read_text().split("<table>")[0]
    assert ("The champion, m000001-aa, cannot be loaded, so the disagreement map and the predicted-vs-real frames "
            "are left out: weights do not match their sha256") in head
