"""Per shape, what more data can still buy: how much a champion's error on episodes fell once it trained on them.

An ensemble disagrees most where it predicts worst, and that is not always where data helps: in
``bench loop`` with per-shape colours the active arm gave the L shape 41 of 96 episodes in every seed
(its error and disagreement are the highest) and the L's error did not move, while the shapes it
starved got worse. What tells the two apart is whether training on a shape's episodes lowers the
error on them.

For each episode the planner scores, ``ShapeProgress`` keeps two numbers: the mean error (ensemble mean,
at the scorer's horizon, 1 by default) of the latest champion that had *not* trained on it ("fresh"), and
that of the first champion after it that *had* ("seen"). A shape's drop is ``(fresh - seen) / fresh`` averaged over its
last ``memory`` episodes that have both. Every shape drops somewhat, because the later champion saw
more data of every kind (in ``bench loop`` 7-20 % a round); what a shape's own data buys is its drop
beyond the smallest one, which ``quotas`` splits a round by, with a floor for every shape. Little
where the model fits a shape as badly as it predicts it (a capacity limit) or already knows it well;
most for a shape it has seen too little of. A shape without such an episode counts as the largest
(so it is tried).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from storage.records import Episode

if TYPE_CHECKING:  # (orchestrator.planner imports this module)
    from orchestrator.planner import Scores


@dataclass
class _Record:
    episode_id: str
    shape: str
    fresh: float
    """Mean error of the latest champion not trained on the episode."""
    fresh_version: str
    seen: float = math.nan
    """Mean error of the first later champion trained on it (NaN until one scored it)."""


class ShapeProgress:
    """Fresh and seen errors of the recent episodes, per shape (see the module docstring)."""

    def __init__(self, memory: int = 16) -> None:
        if memory < 1:
            raise ValueError(f"memory must be >= 1, found {memory}")
        self.memory = memory
        self._done: dict[str, deque[_Record]] = {}
        """Per shape, the last ``memory`` records with both errors."""
        self._waiting: dict[str, dict[str, tuple[Episode, _Record]]] = {}
        """Per shape, the last ``memory`` episodes with a fresh error only, by id (oldest first); they are
        kept whole (frames too) to be scored again, at most ``memory`` per shape."""
        self._turn = 0
        """Which shape the ties of the next ``quotas`` start from (they rotate from call to call)."""

    def record(self, episode: Episode, scores: Scores) -> None:
        """Take one scoring of ``episode`` (one that says whether its champion trained on it, with errors)."""
        if scores.error is None or scores.trained is None:
            return
        finite = scores.error[np.isfinite(scores.error)]
        if not finite.size:
            return
        error, shape, episode_id = float(finite.mean()), episode.meta.shape, episode.meta.episode_id
        waiting = self._waiting.setdefault(shape, {})
        if any(r.episode_id == episode_id for r in self._done.get(shape, ())):
            return  # both errors known (a rollback to a champion that had not seen it changes nothing)
        if not scores.trained:  # the latest fresh error wins (the one nearest the training that follows)
            waiting.pop(episode_id, None)
            waiting[episode_id] = (episode, _Record(episode_id, shape, error, scores.model_version))
            while len(waiting) > self.memory:
                waiting.pop(next(iter(waiting)))
        elif episode_id in waiting:  # the first champion trained on it
            _, rec = waiting.pop(episode_id)
            rec.seen = error
            self._done.setdefault(shape, deque(maxlen=self.memory)).append(rec)

    def waiting(self, version: str) -> list[Episode]:
        """The episodes with a fresh error by a champion other than ``version``: scored again by ``version``,
        they get their seen error if it was trained on them."""
        return [ep for shape in self._waiting.values() for ep, rec in shape.values() if rec.fresh_version != version]

    def _measured(self, shape: str) -> list[_Record]:
        """The shape's recent records with both errors and a fresh one to divide by."""
        return [r for r in self._done.get(shape, ()) if r.fresh > 0]

    def drops(self, shapes: Sequence[str]) -> dict[str, float]:
        """Per shape, the mean of ``(fresh - seen) / fresh`` over its recent episodes; NaN for a shape with none."""
        out = {}
        for shape in shapes:
            done = self._measured(shape)
            out[shape] = float(np.mean([(r.fresh - r.seen) / r.fresh for r in done])) if done else math.nan
        return out

    def counts(self, shapes: Sequence[str]) -> dict[str, int]:
        """Per shape, how many episodes its drop is the mean over."""
        return {shape: len(self._measured(shape)) for shape in shapes}

    def quotas(self, k: int, shapes: Sequence[str], floor: float) -> dict[str, int]:
        """``k`` requests split over ``shapes``: a share ``floor`` equally, the rest in proportion to each
        shape's drop beyond the smallest (an unknown one counts as the largest known; all equal while
        fewer than two are known), rounded by largest remainder; equal remainders go first to the shape
        whose turn it is, the turn moving on by one shape each call (so no shape always gets the extra)."""
        if not shapes or k < 0 or not 0.0 <= floor <= 1.0:
            raise ValueError(f"need shapes, k >= 0 and floor in [0, 1], found {list(shapes)}, {k}, {floor}")
        drops = self.drops(shapes)
        known = [d for d in drops.values() if math.isfinite(d)]
        least = min(known, default=0.0)
        top = max(known, default=0.0) - least
        value = np.array([d - least if math.isfinite(d) else top for d in drops.values()])
        if len(known) < 2 or value.sum() <= 0:
            value = np.ones(len(shapes))
        share = floor / len(shapes) + (1.0 - floor) * value / value.sum()
        exact = k * share
        counts = np.floor(exact).astype(int)
        turn, self._turn = self._turn, self._turn + 1
        order = sorted(range(len(shapes)), key=lambda i: (-(exact[i] - counts[i]), (i - turn) % len(shapes)))
        for i in order[:k - int(counts.sum())]:
            counts[i] += 1
        return {shape: int(c) for shape, c in zip(shapes, counts)}
