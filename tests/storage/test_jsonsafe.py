"""storage.jsonsafe: the one function every JSON we write goes through."""

from __future__ import annotations

import json
import math

from storage.jsonsafe import finite_json


def test_nan_and_infinities_become_null_at_any_depth_and_the_rest_is_kept() -> None:
    value = {"h1": 0.5, "h5": math.nan, "curve": [(1, math.inf), {"x": -math.inf, "n": 3, "s": "nan"}], "ok": True}
    out = finite_json(value)
    assert out == {"h1": 0.5, "h5": None, "curve": [[1, None], {"x": None, "n": 3, "s": "nan"}], "ok": True}
    assert json.loads(json.dumps(out, allow_nan=False)) == out
    assert value["h5"] != value["h5"]  # (the input is left as it was)
