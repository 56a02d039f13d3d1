"""One retrain job in this process: under the retrain lock, train a candidate, evaluate it, gate it.

``activecollect retrain`` (the child process ``orchestrator.scheduler`` starts, or a
system cron job) and ``bench loop`` run it. It imports the trainer, and with it torch;
the scheduler, which only starts and watches jobs, does not.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from orchestrator.scheduler import note_phase, retrain_lock
from storage.catalog import Catalog
from storage.errors import StorageError
from storage.models import ModelRegistry
from uncertainty.config import TrainConfig
from uncertainty.train import train_candidate


def run_retrain(data_dir: Path, cfg: TrainConfig, wait: bool = False, keep_models: int | None = None) -> dict:
    """One retrain job under the lock: train on the train snapshot, evaluate, register, gate.

    With ``cfg.from_champion`` the champion's weights are fine-tuned on all the data (a
    fresh model while there is no champion yet). With ``keep_models`` the registry is then
    pruned to the champion's rollback chain of that many (``ModelRegistry.prune``).

    Returns ``{"version", "promoted", "reason", "metrics", "champion", "pruned", "prune_error"}``; a
    prune that fails does not fail the job (the gate has decided by then): ``prune_error`` says why. Raises
    ``orchestrator.scheduler.RetrainBusyError`` when another job holds the lock (and ``wait`` is False), and
    whatever training raises (``uncertainty`` and ``storage`` errors); in every failure
    the champion is untouched, because only the gate at the very end promotes.
    """
    data_dir = Path(data_dir)
    with retrain_lock(data_dir, wait=wait):
        catalog = Catalog(data_dir)
        registry = ModelRegistry(data_dir)
        if cfg.from_champion and registry.champion() is None:  # the first retrain has nothing to start from
            cfg = dataclasses.replace(cfg, from_champion=False)
        note_phase(data_dir, "training")
        result = train_candidate(catalog, registry, cfg)
        pruned, prune_error = [], None
        if keep_models is not None:
            try:
                pruned = registry.prune(keep_models).pruned
            except (StorageError, OSError) as exc:
                prune_error = f"pruning the registry failed: {exc}"
        note_phase(data_dir, "done")
        return {"version": result.version, "promoted": result.decision.promoted,
                "reason": result.decision.reason, "champion": registry.champion(), "pruned": pruned,
                "prune_error": prune_error,
                "metrics": {k: v for k, v in result.metrics.items() if not isinstance(v, (list, dict))}}
