"""``orchestrator.bounded.remember``: the newest entries only, a key put again counting as new."""

from __future__ import annotations

from collections import OrderedDict

from orchestrator.bounded import remember


def test_keeps_the_newest_and_a_key_put_again_is_newest() -> None:
    kept: OrderedDict[str, int] = OrderedDict()
    for n, key in enumerate("abc"):
        remember(kept, key, n, 3)
    remember(kept, "a", 9, 3)  # now the newest: "b" is the oldest
    remember(kept, "d", 4, 3)
    assert list(kept.items()) == [("c", 2), ("a", 9), ("d", 4)]


def test_a_cap_below_what_is_kept_forgets_down_to_it() -> None:
    kept = OrderedDict((n, n) for n in range(5))
    remember(kept, 5, 5, 2)
    assert list(kept) == [4, 5]
