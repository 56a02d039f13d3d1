"""The registry's champion, loaded when needed: the planner's scorer and the dashboard's frames.

``ChampionScorer`` is the ``planner.Scorer`` backed by the champion; it reloads
(hot-swaps) when the champion changes, whoever promoted it. ``FramesSource`` draws
the dashboard's predicted-vs-real picture with it.

Torch (about 2 s and 350 MB) is imported when the first champion is loaded, not when
this module is: ``serve`` and ``dashboard`` over a registry with no champion yet never
load it. The two imports inside functions below are for that start-up cost, not to
break a cycle (both point down: ``orchestrator`` -> ``uncertainty``).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from orchestrator.planner import Scores
from storage.catalog import Catalog
from storage.checkpoint_files import file_state
from storage.errors import RegistryError, StorageUnavailableError
from storage.models import ModelRegistry
from storage.records import Episode

if TYPE_CHECKING:
    from uncertainty.ensemble import Ensemble

log = logging.getLogger(__name__)


def make_torch_deterministic() -> None:
    """This process's torch from now on computes the same result from the same input on the GPU too (the CPU's
    kernels do already, at a fixed thread count; cuDNN's and cuBLAS's fastest do not, so two GPU runs of one
    ``bench loop`` differed by up to 0.8 %). Deterministic algorithms only, cuDNN's autotuner off, and the cuBLAS
    workspace its deterministic mode needs, which takes effect only if set before the process's first CUDA
    call. An operation torch has no deterministic kernel for warns (naming it) rather than fails. Process-wide.
    """
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    import torch  # (only ever called where torch is being loaded anyway)
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark = False


def limit_torch_threads(threads: int) -> None:
    """Give torch at most ``threads`` intra-op threads in this process (0: leave its setting alone).

    ``serve`` scores in its own process while each retrain runs in a child process. Both busy
    with torch's default, a thread per core each, their OpenMP threads spin against each other:
    on 2 cores the retrain took 9x as long as alone and the scoring ran at 0.10 of its speed;
    with one scoring thread and the retrain on the other core, 1.33x and 0.95 (BENCHMARKS.md,
    "Scoring beside a retrain"; ``serve --scoring-threads``, ``--retrain-threads``).

    Process-wide, with torch's one exception: a thread takes the setting on its first torch
    call, so one that used torch before keeps its count (call this before starting threads).
    """
    if threads:
        import torch  # (only ever called where torch is being loaded anyway)
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)


class ChampionScorer:
    """Scores episodes with the current champion; None while there is none.

    Every call compares the registry's champion with the loaded one and reloads on a
    change, so a promotion by the scheduler, by ``activecollect retrain`` from cron or
    by an operator's rollback is picked up without a restart. ``reload()`` forces it.

    A champion that cannot be loaded (damaged weights) is logged once and tried again when
    its weights file changes (restored), another model becomes champion, or ``RETRY_S`` have
    passed (a read error that passes); meanwhile the one loaded before keeps scoring, and
    ``problem`` says why. A registry that cannot be read now (its database locked past the busy
    timeout: the dashboard's is 2 s) is no sign of damage: tried again after ``BUSY_RETRY_S``.
    """

    RETRY_S = 60.0
    BUSY_RETRY_S = 5.0

    def __init__(self, data_dir: Path, device: str = "cpu",
                 observe: Callable[[float], None] = lambda seconds: None, with_error: bool = False,
                 error_horizon: int = 1, threads: int = 0) -> None:
        if threads < 0:
            raise ValueError(f"threads must be >= 0, found {threads}")
        self.data_dir = Path(data_dir)
        self.device = device
        self.threads = threads
        """Torch's intra-op threads in this whole process, set when a champion is loaded (0: leave torch's own
        setting, one per core). See ``limit_torch_threads``."""
        self.observe = observe
        self.with_error = with_error
        """Scores also carry the ensemble mean's error per step and whether the champion trained on the episode."""
        self.error_horizon = error_horizon
        """The error's horizon (``uncertainty.score.prediction_error``)."""
        self._trained_on: tuple[str | None, frozenset[str] | None, float] = (None, None, 0.0)
        # (version, the episodes it was trained on or None when not known, when to read them again): one
        # tuple, read and replaced without the lock
        self._lock = threading.Lock()
        self._local = threading.local()
        self.version: str | None = None
        self.ensemble: Ensemble | None = None
        self.problem: str | None = None
        """Why the registry's champion is not the one loaded (None when it is)."""
        self._failed: tuple[str, tuple[int, int, int, int] | None] | None = None
        self._retry_at = 0.0
        self._said: frozenset[bool] = frozenset()
        """The kinds of failure (busy or not) logged above DEBUG for ``_failed``."""

    def _registry(self) -> ModelRegistry:
        if not hasattr(self._local, "registry"):
            self._local.registry = ModelRegistry(self.data_dir, make_models_dir=False)  # (it only reads)
        return self._local.registry

    def reload(self) -> str | None:
        """Load the registry's champion if it is not the one loaded; returns the version loaded."""
        registry = self._registry()
        with self._lock:
            # Read under the lock: a value read before it may be one that another thread, holding it, has
            # already replaced by a newer champion, and loading it would switch back to a retired model.
            champion = registry.champion()
            if champion == self.version:
                self.problem = None
                return champion
            if champion is None:
                self.version, self.ensemble, self.problem = None, None, None
                return None
            attempt = (champion, file_state(registry.get(champion).weights_path))
            if attempt == self._failed and time.monotonic() < self._retry_at:
                return self.version  # nothing has changed since it failed: not read (and hashed) again yet
            from uncertainty.checkpoint import load_ensemble  # torch: start-up cost, see the module docstring
            limit_torch_threads(self.threads)
            try:
                ensemble = load_ensemble(registry, champion, self.device)
            except RegistryError as exc:  # a corrupt checkpoint: keep scoring with the one we have
                busy = isinstance(exc, StorageUnavailableError)
                # each kind logged once, not every retry: damage found after a busy read is still an ERROR
                said = self._said if attempt == self._failed else frozenset()
                level = logging.DEBUG if busy in said else logging.WARNING if busy else logging.ERROR
                self._failed, self._said = attempt, said | {busy}
                self._retry_at = time.monotonic() + (self.BUSY_RETRY_S if busy else self.RETRY_S)
                self.problem = f"cannot load champion {champion}{' now' if busy else ''}: {exc}"
                log.log(level, "could not load champion %s%s, keeping %s: %s", champion,
                        f" now (trying again in {self.BUSY_RETRY_S:g} s)" if busy else "", self.version, exc)
                return self.version
            self.version, self.ensemble, self.problem, self._failed = champion, ensemble, None, None
            log.info("scorer now uses champion %s", champion)
            return champion

    def loaded(self) -> tuple[str | None, Ensemble | None]:
        """The version loaded and its ensemble, read together (another thread may swap them at any time)."""
        with self._lock:
            return self.version, self.ensemble

    def _training_episodes(self, version: str) -> frozenset[str] | None:
        """The episodes ``version`` was trained on (None: not recorded, or not readable), read once per champion;
        a read that failed for a reason that passes is tried again after ``RETRY_S``."""
        known, ids, retry_at = self._trained_on
        if known == version and (ids is not None or time.monotonic() < retry_at):
            return ids
        retry_at = float("inf")
        try:
            snap = self._registry().snapshot(version)
        except RegistryError as exc:  # the weights loaded; only which episodes it saw is unknown
            if isinstance(exc, StorageUnavailableError) or isinstance(exc.__cause__, OSError):
                retry_at = time.monotonic() + self.RETRY_S
            log.warning("champion %s: its training episodes cannot be read, scores say nothing of them%s: %s",
                        version, " for now" if retry_at < float("inf") else "", exc)
            snap = None
        else:
            if snap is None:
                log.info("champion %s has no record of its training episodes (registered before models kept "
                         "them): scores say nothing of them", version)
        ids = None if snap is None else frozenset(snap.ids)
        self._trained_on = (version, ids, retry_at)
        return ids

    def __call__(self, episode: Episode) -> Scores | None:
        self.reload()
        version, ensemble = self.loaded()
        if ensemble is None or version is None:
            return None
        if ensemble.config.image_size != episode.frames.shape[1]:
            log.warning("episode %s has %dpx frames, champion %s predicts %dpx; not scored",
                        episode.meta.episode_id, episode.frames.shape[1], version, ensemble.config.image_size)
            return Scores(version, np.full(len(episode), np.nan))
        start = time.perf_counter()
        per_step = ensemble.disagreement(episode.frames, episode.actions)
        self.observe(time.perf_counter() - start)
        return self.scores(episode, per_step, ensemble, version)

    def scores(self, episode: Episode, per_step: np.ndarray, ensemble: Ensemble, version: str) -> Scores:
        """``per_step`` as the ``Scores`` of ``episode`` by the loaded ``ensemble`` (its ``version``), with the
        error and whether it trained on the episode when ``with_error``."""
        if not self.with_error:
            return Scores(version, per_step)
        from uncertainty.score import prediction_error  # torch is loaded: an ensemble is
        trained_on = self._training_episodes(version)
        error = prediction_error(ensemble, episode.frames, episode.actions, self.error_horizon)
        return Scores(version, per_step, error,
                      None if trained_on is None else episode.meta.episode_id in trained_on)


class FramesSource:
    """The dashboard's predicted-vs-real PNG: the champion on a few eval episodes, redrawn per champion."""

    def __init__(self, scorer: ChampionScorer, catalog: Catalog, samples: int = 3) -> None:
        self.scorer = scorer
        self.catalog = catalog
        self.samples = samples
        self._cache: tuple[str | None, bytes] = (None, b"")
        self._lock = threading.Lock()

    def __call__(self) -> bytes:
        self.scorer.reload()
        split = self.catalog.eval_split()
        version, ensemble = self.scorer.loaded()  # one pair: the picture is cached under its ensemble's version
        if version is None or split is None or ensemble is None:
            return b""
        from orchestrator.report import frames_png  # torch: start-up cost, see the module docstring
        with self._lock:
            if self._cache[0] != version:
                episodes = [self.catalog.load(i) for i in split.ids[:self.samples]]
                self._cache = (version, frames_png(ensemble, episodes))
            return self._cache[1]
