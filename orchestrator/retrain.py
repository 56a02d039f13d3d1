"""One retrain job in this process: under the retrain lock, train a candidate, evaluate it, gate it.

``activecollect retrain`` (the child process ``orchestrator.scheduler`` starts, or a
system cron job) and ``bench loop`` run it. It imports the trainer, and with it torch;
the scheduler, which only starts and watches jobs, does not.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from orchestrator.retrainlock import note_phase, retrain_lock
from storage.catalog import Catalog
from storage.errors import StorageError
from storage.database import MODELS_DIR
from storage.models import ModelRegistry, PruneResult
from storage.strays import MODEL_ORPHANS_DIR
from uncertainty.config import TrainConfig
from uncertainty.train import train_candidate

log = logging.getLogger(__name__)

#: The reason a candidate left by an earlier job gets when the next job finds it.
ABANDONED = "abandoned: the job that registered it ended before its gate (rejected by the next training job)"


class JobRegistry(ModelRegistry):
    """The registry as a training job uses it: the version it registers is noted in the lock file at once.

    So a job that dies before reporting, its gate passed or not, can still be told by what it left: the
    scheduler reads the version there and the model's fate in the registry (``RetrainScheduler``).
    """

    def register(self, *args: Any, **kwargs: Any) -> str:
        version = super().register(*args, **kwargs)
        note_phase(self.data_dir, "registered", version=version)
        return version


def abandoned_note(versions: list[str]) -> str:
    """One line for the operator on the candidates ``training_job`` rejected."""
    return f"rejected {', '.join(versions)}: left as candidates by a job that ended before its gate"


def prune_warnings(result: PruneResult) -> list[str]:
    """One line for the operator per model whose files ``result``'s prune could not delete
    (``PruneResult.not_deleted``), and per checkpoint folder no row names that it could not move aside
    (``PruneResult.not_moved``): it stays in ``models/``, taking its space, which a prune is there to free. Logged
    too, as ``uncertainty.train`` logs its own warnings (the scheduler logs a job's from its report)."""
    lines = [f"checkpoint folder {MODELS_DIR}/{version} (no model row names it: a register killed before its "
             f"commit) could not be moved aside to {MODEL_ORPHANS_DIR}/ ({why}); it stays where it is, unused, "
             "until a later prune or sweep" for version, why in result.not_moved.items()]
    lines += [f"the prune could not delete the files of {version} ({why}); a model still whole stays unpruned and "
              "usable" for version, why in result.not_deleted.items()]
    for line in lines:
        log.warning("%s", line)
    return lines


@contextlib.contextmanager
def training_job(data_dir: Path, wait: bool = False) -> Iterator[tuple[Catalog, ModelRegistry, list[str]]]:
    """Hold the retrain lock for one training job (``retrain`` and ``train`` alike).

    Every job registers and gates its candidate under this lock, so a ``candidate`` found
    now was left by a job that died (or whose gate failed) in between: it is rejected with
    ``ABANDONED`` first, so that ``prune`` may free it. Yields the catalog, the registry (a
    ``JobRegistry``: what it registers is noted in the lock file) and the versions so rejected.
    Raises ``RetrainBusyError`` like ``retrain_lock``.
    """
    data_dir = Path(data_dir)
    with retrain_lock(data_dir, wait=wait):
        registry = JobRegistry(data_dir)
        abandoned = registry.reject_candidates(ABANDONED)
        note_phase(data_dir, "training")
        yield Catalog(data_dir), registry, abandoned
        note_phase(data_dir, "done")


def run_retrain(data_dir: Path, cfg: TrainConfig, wait: bool = False, keep_models: int | None = None) -> dict:
    """One retrain job under the lock: train on the train snapshot, evaluate, register, gate.

    With ``cfg.from_champion`` the champion's weights are fine-tuned on all the data (a
    fresh model while there is no champion yet; when the champion's checkpoint is damaged, the newest sound
    model of its rollback chain or a fresh one, which the gate lets replace it: see
    ``uncertainty.train.warm_start``). With ``keep_models`` the registry is then pruned to the champion's
    rollback chain of that many (``ModelRegistry.prune``).

    Returns ``{"version", "promoted", "reason", "metrics", "champion", "pruned", "prune_error", "abandoned",
    "quarantined", "warnings"}`` (``abandoned``: candidates earlier jobs left, rejected first, see
    ``training_job``; ``quarantined``: train episodes found missing or damaged, see
    ``uncertainty.data.load_train``; ``warnings``: ``TrainResult.warnings``, one line each, then one per
    checkpoint folder no row names that the prune could not move aside, see ``prune_warnings``); a prune that
    fails does not fail the job (the gate has decided by then): ``prune_error`` says why. Raises
    ``orchestrator.retrainlock.RetrainBusyError`` when another job holds the lock (and ``wait`` is False), and
    whatever training raises (``uncertainty`` and ``storage`` errors; ``RegistryUnavailableError`` when the
    checkpoint to warm-start from cannot be read now); in every failure the champion is untouched, because
    only the gate at the very end promotes.
    """
    with training_job(data_dir, wait=wait) as (catalog, registry, abandoned):
        if cfg.from_champion and registry.champion() is None:  # the first retrain has nothing to start from
            cfg = dataclasses.replace(cfg, from_champion=False)
        result = train_candidate(catalog, registry, cfg)
        pruned, prune_error, warnings = [], None, list(result.warnings)
        if keep_models is not None:
            try:
                prune = registry.prune(keep_models)
            except (StorageError, OSError) as exc:
                prune_error = f"pruning the registry failed: {exc}"
            else:
                pruned = prune.pruned
                warnings += prune_warnings(prune)
        return {"version": result.version, "promoted": result.decision.promoted,
                "reason": result.decision.reason, "champion": registry.champion(), "pruned": pruned,
                "prune_error": prune_error, "abandoned": abandoned, "quarantined": result.quarantined,
                "warnings": warnings,
                "metrics": {k: v for k, v in result.metrics.items() if not isinstance(v, (list, dict))}}
