"""Memory bounded against any peer: a dict that keeps its newest entries only."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any


def remember(kept: OrderedDict[Any, Any], key: Any, value: Any, most: int) -> None:
    """Put ``key`` in ``kept`` as its newest, forgetting the oldest past ``most`` entries."""
    kept[key] = value
    kept.move_to_end(key)
    while len(kept) > most:
        kept.popitem(last=False)
