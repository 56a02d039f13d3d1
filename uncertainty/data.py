"""Training and evaluation windows cut from catalog episodes.

A window is what the predictor learns from: ``C`` context frames, the action(s)
taken after the last of them, and the true next frame(s). All frames of a set of
episodes are kept once, as uint8, and windows are index arrays into them, so
a few thousand windows cost no more memory than their episodes.

Training reads only the catalog's ``train`` snapshot and refuses any episode that
is also in the pinned eval split, and leaves out (and reports) any that replays an eval
episode under another id (``storage.eval_split.replays``: catalogs index none since they
refuse them, older ones may hold some); evaluation reads only the eval split.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np
import torch

from storage.errors import DAMAGED_EPISODE_ERRORS
from storage.quarantine import clean_reason, looks_unmounted
from storage.records import Episode
from storage.rows import Snapshot
from uncertainty.errors import DataError
from uncertainty.model import PredictorConfig

log = logging.getLogger(__name__)


class CatalogLike(Protocol):
    """What this module needs of ``storage.catalog.Catalog``."""

    def snapshot(self, split: str = "train"): ...
    def eval_split(self): ...
    def load(self, episode_id: str) -> Episode: ...
    def quarantine(self, episode_id: str, reason: str, only_if_damaged: bool = False): ...
    def get(self, episode_id: str): ...
    def replays(self, split: str = "train") -> dict[str, str]: ...


@dataclass
class Windows:
    """Windows over a set of episodes: index arrays into one uint8 frame store."""

    frames: torch.Tensor
    """(F, 3, H, W) uint8: every frame of every episode, episodes back to back."""
    actions: torch.Tensor
    """(F, A) float32 raw actions aligned with ``frames``."""
    context: torch.Tensor
    """(N, C) int64: frame indices of each window's context, oldest first."""
    action_idx: torch.Tensor
    """(N, H) int64: indices (into ``actions``) of the actions to apply, in order."""
    target: torch.Tensor
    """(N, H) int64: frame indices of the true next frames."""
    episode: np.ndarray
    """(N,) int: which episode (position in ``episode_ids``) each window comes from."""
    step: np.ndarray
    """(N,) int: the step t of the last context frame."""
    episode_ids: list[str]
    """Ids of the episodes, in store order."""

    def __len__(self) -> int:
        return len(self.context)

    @property
    def horizon(self) -> int:
        return self.target.shape[1]

    def subset(self, idx: np.ndarray) -> "Windows":
        """The windows at ``idx`` (same frame store)."""
        t = torch.as_tensor(np.asarray(idx, dtype=np.int64))
        return Windows(self.frames, self.actions, self.context[t], self.action_idx[t], self.target[t],
                       self.episode[idx], self.step[idx], self.episode_ids)

    def batch(self, idx: torch.Tensor, device: torch.device | str) -> tuple[torch.Tensor, ...]:
        """Float tensors for windows ``idx`` (any shape S): context (*S,C,3,H,W), actions (*S,H,A),
        targets (*S,H,3,H,W)."""
        ctx = self.frames[self.context[idx]].to(device).float().div_(255.0)   # (*S, C, 3, H, W)
        act = self.actions[self.action_idx[idx]].to(device)                   # (*S, H, A)
        tgt = self.frames[self.target[idx]].to(device).float().div_(255.0)    # (*S, H, 3, H, W)
        return ctx, act, tgt


def build_windows(episodes: Sequence[Episode], config: PredictorConfig, horizon: int = 1,
                  stride: int = 1) -> Windows:
    """Every window with ``config.context`` frames of context and ``horizon`` successors.

    ``stride`` keeps every stride-th start step. Raises ``DataError`` when an
    episode's frames do not match the config or no episode is long enough.
    """
    if horizon < 1 or stride < 1:
        raise DataError(f"horizon and stride must be >= 1, found {horizon} and {stride}")
    c, size = config.context, config.image_size
    frames, actions, ctx, act, tgt, epi, steps = [], [], [], [], [], [], []
    offset = 0
    for i, ep in enumerate(episodes):
        if ep.frames.shape[1:] != (size, size, 3):
            raise DataError(f"episode {ep.meta.episode_id}: frames must be ({size},{size},3), "
                            f"found {ep.frames.shape[1:]}; train with image_size={ep.frames.shape[1]}")
        t = len(ep)
        s = np.arange(c - 1, t - horizon, stride)                      # (n,) valid start steps
        frames.append(torch.from_numpy(np.ascontiguousarray(ep.frames)).permute(0, 3, 1, 2))  # (T, 3, H, W)
        actions.append(torch.from_numpy(np.asarray(ep.actions, dtype=np.float32)))            # (T, A)
        ctx.append(offset + s[:, None] + np.arange(-c + 1, 1)[None, :])  # (n, C)
        act.append(offset + s[:, None] + np.arange(horizon)[None, :])    # (n, H)
        tgt.append(offset + s[:, None] + np.arange(1, horizon + 1)[None, :])  # (n, H)
        epi.append(np.full(len(s), i))
        steps.append(s)
        offset += t
    n = sum(len(s) for s in steps)
    if n == 0:
        raise DataError(f"no episode of {len(episodes)} is long enough for context {c} and horizon {horizon}")
    return Windows(
        frames=torch.cat(frames).contiguous(), actions=torch.cat(actions),
        context=torch.as_tensor(np.concatenate(ctx), dtype=torch.int64),
        action_idx=torch.as_tensor(np.concatenate(act), dtype=torch.int64),
        target=torch.as_tensor(np.concatenate(tgt), dtype=torch.int64),
        episode=np.concatenate(epi), step=np.concatenate(steps),
        episode_ids=[ep.meta.episode_id for ep in episodes])


def action_stats(episodes: Sequence[Episode]) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension mean and std of the actions (std floored at 1e-3); stored in checkpoints."""
    acts = np.concatenate([np.asarray(ep.actions, dtype=np.float64) for ep in episodes])  # (sum T, A)
    return acts.mean(axis=0).astype(np.float32), np.maximum(acts.std(axis=0), 1e-3).astype(np.float32)


def member_indices(windows: Windows, members: int, bootstrap: bool,
                   rng: np.random.Generator) -> list[np.ndarray]:
    """Window indices each member trains on: all of them, or a bootstrap resample of the episodes.

    A bootstrap member sees each drawn episode's windows once per time it was drawn; only
    episodes with at least one window are drawn, so no member's pool is empty.
    """
    everything = np.arange(len(windows))
    if not bootstrap:
        return [everything for _ in range(members)]
    by_episode = [np.flatnonzero(windows.episode == e) for e in range(len(windows.episode_ids))]
    by_episode = [w for w in by_episode if len(w)]  # episodes too short for a window are not drawn
    n_eps = len(by_episode)
    out = []
    for _ in range(members):
        drawn = rng.integers(0, n_eps, size=n_eps)
        out.append(np.concatenate([by_episode[e] for e in drawn]))
    return out


@dataclass
class TrainData:
    """The training episodes of one catalog snapshot."""

    episodes: list[Episode]
    snapshot: Snapshot
    """The episodes loaded (ids and sha256s, sorted by id): what the model is trained on."""
    episode_ids: list[str]
    """Their ids in training order."""
    quarantined: list[str] = field(default_factory=list)
    """Episodes of the snapshot whose files were found missing or damaged, and quarantined."""
    replays: dict[str, str] = field(default_factory=dict)
    """Episodes of the snapshot left out because they replay an eval episode: {id: the eval episode's id}."""
    other_size: dict[str, int] = field(default_factory=dict)
    """Episodes of the snapshot left out because their frames have another size than asked: {id: their size}."""
    image_size: int | None = None
    """The frame size asked for (None: any)."""

    @property
    def snapshot_id(self) -> str:
        return self.snapshot.snapshot_id

    @property
    def warnings(self) -> list[str]:
        """One line each for what the snapshot held that was not trained on, other than ``quarantined``."""
        return ([replays_note(self.replays)] if self.replays else []) + \
            ([other_size_note(self.other_size, self.image_size)] if self.other_size else [])


def replays_note(replays: dict[str, str]) -> str:
    """One line for the operator on the train episodes left out as replays of eval episodes ({id: eval id})."""
    shown = ", ".join(f"{i} (of {e})" for i, e in sorted(replays.items())[:3])
    return (f"left out {len(replays)} train episode(s) that replay eval episodes: {shown}"
            f"{f' and {len(replays) - 3} more' if len(replays) > 3 else ''} (indexed before the catalog refused "
            "such copies; training on them would leak the eval split: `activecollect episodes quarantine` them)")


def other_size_note(other_size: dict[str, int], image_size: int | None) -> str:
    """One line for the operator on the train episodes left out for their frame size ({id: size})."""
    shown = ", ".join(f"{i} ({px}px)" for i, px in sorted(other_size.items())[:3])
    return (f"left out {len(other_size)} train episode(s) whose frames are not the eval split's {image_size}px: "
            f"{shown}{f' and {len(other_size) - 3} more' if len(other_size) > 3 else ''} (indexed before the "
            "catalog held one frame size; a model predicts one size: `activecollect episodes quarantine` them)")


def load_train(catalog: CatalogLike, max_episodes: int | None = None, image_size: int | None = None) -> TrainData:
    """Loads the ``train`` snapshot; raises ``DataError`` if it is empty or overlaps the eval split.

    An episode that replays an eval episode under another id (``Catalog.replays``: indexed before the catalog
    refused such copies) is left out, named in ``TrainData.replays`` and in a warning, logged; the snapshot is
    then that of the others. An episode whose file is missing or no longer holds the bytes indexed is quarantined
    (``Catalog.quarantine``, which keeps its row and whatever is left of its file) and left out, so one
    lost file does not stop every retrain: the snapshot is then that of the episodes kept (as with
    ``max_episodes``: of those loaded). When most
    of them are (more than one and more than half: a disk not mounted, not a lost file), nothing is
    quarantined and ``DataError`` says so. With ``image_size`` (the eval split's) an episode whose frames have
    another size (indexed before the catalog held one size) is left out like a replay (``TrainData.other_size``).
    """
    snap = catalog.snapshot(split="train")
    ids = list(snap.ids)
    split = catalog.eval_split()
    if split is not None:
        leaked = sorted(set(ids) & set(split.ids))
        if leaked:
            raise DataError(f"train snapshot {snap.snapshot_id} holds {len(leaked)} eval-split episodes "
                            f"(first {leaked[0]}); the eval split must never be trained on")
    in_snapshot = set(ids)
    replays = {i: e for i, e in catalog.replays("train").items() if i in in_snapshot}
    if replays:
        log.warning("%s", replays_note(replays))
        ids = [i for i in ids if i not in replays]
        if not ids:
            raise DataError(f"every train episode ({len(replays)}) replays an eval episode: training on them would "
                            "leak the eval split; collect others (another --seed)")
    if not ids:
        raise DataError("the catalog has no train episodes; collect some first")
    episodes, kept, damaged, other_size = [], [], [], {}

    def keep(episode_id: str, episode: Episode) -> None:
        size = int(episode.frames.shape[1])
        if image_size is not None and size != image_size:
            other_size[episode_id] = size
        else:
            episodes.append(episode)
            kept.append(episode_id)

    for episode_id in ids:
        if max_episodes is not None and len(kept) == max_episodes:
            break
        try:
            episode = catalog.load(episode_id)
        except DAMAGED_EPISODE_ERRORS as exc:
            # one quarantined since the snapshot (`episodes quarantine` beside this job moved its file aside) is
            # left out, and is not a damaged file: nor a sign of an unmounted disk
            if not catalog.get(episode_id).quarantined:
                damaged.append((episode_id, exc))
        else:
            keep(episode_id, episode)
    if looks_unmounted(len(damaged), len(damaged) + len(kept)):
        raise DataError(f"the files of {len(damaged)} of {len(damaged) + len(kept)} train episodes are missing "
                        f"or damaged (first: {damaged[0][1]}); nothing was quarantined: check that the data "
                        "directory's disk is there and readable, then `activecollect episodes verify --quarantine`")
    lost = []
    for episode_id, exc in damaged:
        reason = clean_reason(f"found by a training job: {exc}")
        row = catalog.quarantine(episode_id, reason, only_if_damaged=True)
        if row.quarantined == reason:
            lost.append(episode_id)
        elif not row.quarantined:  # repaired (its bytes ingested again) since it was read
            keep(episode_id, catalog.load(episode_id))
        # else quarantined by someone else since the snapshot (`episodes quarantine` moved its intact file to
        # DATA/quarantine/): left out, but not this job's finding of a missing or damaged file
    if not kept and other_size:
        first, px = min(other_size.items())
        raise DataError(f"no train episode has the eval split's {image_size}px frames: {len(other_size)} of another "
                        f"size (first {first} at {px}px, indexed before the catalog held one frame size)"
                        f"{f' and {len(lost)} missing or damaged' if lost else ''}; collect {image_size}px ones")
    if not kept:
        raise DataError(f"the files of all {len(lost)} train episodes are missing or damaged (quarantined "
                        "now); restore them from a backup (activecollect ingest), or collect new ones")
    if other_size:
        log.warning("%s", other_size_note(other_size, image_size))
    sha256 = dict(zip(snap.ids, snap.sha256s))
    return TrainData(episodes, Snapshot.of(sorted((i, sha256[i]) for i in kept)), kept, lost, replays,
                     other_size, image_size)


def load_eval(catalog: CatalogLike) -> tuple[list[Episode], str]:
    """The pinned eval split's episodes and hash; raises ``DataError`` when none is pinned."""
    split = catalog.eval_split()
    if split is None or not split.ids:
        raise DataError("no eval split is pinned in the catalog; create one: `activecollect eval-split create`, "
                        "or `ingest --split eval` then `eval-split pin`")
    return [catalog.load(i) for i in split.ids], split.hash
