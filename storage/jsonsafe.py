"""JSON without NaN: what every ``--json``, ``summary.json``, dashboard answer and model row is written through.

A diverged candidate's NaN eval error, or the h5/h10 error of episodes too short to measure it, would otherwise
make JSON that strict parsers (browsers, jq, Prometheus tooling) refuse.
"""

from __future__ import annotations

import math
from typing import Any


def finite_json(obj: Any) -> Any:
    """A copy of ``obj`` (dicts, lists, tuples as lists) with every NaN and infinity as None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj
