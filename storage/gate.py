"""The promotion gate's judgement: is a candidate measurably better than the champion?

Pure functions over evaluated models (anything with a version, metrics and the hash of the
eval split they were measured on); ``storage.models.ModelRegistry.gate`` applies the verdict
to the registry in one transaction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

DEFAULT_METRIC = "h1_mse"
DEFAULT_MIN_REL_IMPROVEMENT = 0.02


class Evaluated(Protocol):
    """What the gate reads of a model (``storage.models.ModelRecord`` is one)."""

    version: str
    metrics: dict[str, Any]
    eval_split_hash: str


@dataclass(frozen=True)
class GateDecision:
    """What the promotion gate decided, and why, in words an operator can act on."""

    promoted: bool
    """True when the candidate is now the champion."""
    reason: str
    """One sentence: the comparison made, or the check that failed."""
    version: str = ""
    """The candidate."""
    champion_before: str | None = None
    """The champion when the gate ran (None for the first model); for a candidate an operator promoted before its
    gate ran, the champion before that promotion."""
    metric: str = DEFAULT_METRIC
    """The metric compared."""
    candidate_value: float | None = None
    """The candidate's value of ``metric`` (None when missing)."""
    champion_value: float | None = None
    """The champion's value of ``metric`` (None when there was no champion)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "promoted": self.promoted, "reason": self.reason, "version": self.version,
            "champion_before": self.champion_before, "metric": self.metric,
            "candidate_value": self.candidate_value, "champion_value": self.champion_value,
        }


def non_finite(metrics: dict[str, Any], metric: str) -> str | None:
    """Name the first number that matters which is missing or not finite, or None if all are fine.

    The numbers that matter are the gate metric and every horizon-1 metric (``h1_*``): a diverged
    model is NaN there. Longer horizons may be NaN by construction (episodes too short to roll out).
    """
    value = metrics.get(metric)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f"{metric} is missing or not a number (found {value!r})"
    return diverged(metrics, metric)


def diverged(metrics: dict[str, Any], metric: str = DEFAULT_METRIC) -> str | None:
    """Name the first number that matters (``non_finite``'s) which is there and not finite, or None: what even
    the operator's ``promote`` refuses (a diverged model predicts NaN, so its scores would rank nothing)."""
    for key in sorted(k for k in metrics if k == metric or k.startswith("h1_")):
        v = metrics[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isfinite(v):
            return f"{key} is not finite ({v})"
    return None


def judge(rec: Evaluated, champ: Evaluated | None, metric: str, min_rel: float,
          split: str | None, champ_unusable: str = "") -> tuple[bool, str, float | None]:
    """(promote?, reason, champion's value) for ``rec`` against ``champ``; no side effects.

    ``champ_unusable``: why the champion's weights cannot serve (failed sha256, missing); then any
    candidate that passes the split and finiteness checks replaces it, whatever the metrics say."""
    expected = split if split is not None else (champ.eval_split_hash if champ else None)
    if expected is not None and rec.eval_split_hash != expected:
        return False, (f"wrong eval split: {rec.version} was evaluated on {rec.eval_split_hash}, "
                       f"the current eval split is {expected}"), None
    bad = non_finite(rec.metrics, metric)
    if bad is not None:
        return False, f"metrics not finite: {bad}", None
    value = float(rec.metrics[metric])
    if champ is None:
        return True, f"first champion: {metric} {value:.6g} on eval split {rec.eval_split_hash}", None
    if champ_unusable:
        return True, (f"{metric} {value:.6g} replaces champion {champ.version}, whose weights are unusable "
                      f"({champ_unusable})"), None
    if champ.eval_split_hash != rec.eval_split_hash:
        return False, (f"not comparable: champion {champ.version} was evaluated on "
                       f"{champ.eval_split_hash}, {rec.version} on {rec.eval_split_hash}; "
                       f"promote {rec.version} by hand (models promote) if it should serve"), None
    champ_value = champ.metrics.get(metric)
    if not isinstance(champ_value, (int, float)) or not math.isfinite(champ_value):
        return True, (f"{metric} {value:.6g} replaces champion {champ.version}, whose {metric} "
                      f"is not a finite number ({champ_value!r})"), None
    bar = champ_value * (1 - min_rel)
    rel = (champ_value - value) / champ_value if champ_value else 0.0
    words = (f"{metric} {value:.6g} vs champion {champ.version} {champ_value:.6g} "
             f"({rel:+.1%} relative improvement; needs >= {min_rel:.1%}, i.e. < {bar:.6g})")
    if value < bar:
        return True, f"promoted: {words}", float(champ_value)
    return False, f"not better enough: {words}", float(champ_value)
