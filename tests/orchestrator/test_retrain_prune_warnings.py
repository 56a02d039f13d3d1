"""A retrain that prunes (``keep_models``) says which checkpoint folders no row names it could not move aside: one
line each in its ``warnings``, which the scheduler logs, and in its own log. A real training job on a real
catalog (the pymunk simulation, a tiny ensemble on the CPU); the failing rename injected at its one OS call (a
full disk), as no disk here can be made to refuse one."""

from __future__ import annotations

import errno
import logging


from orchestrator.retrain import run_retrain
from storage.models import ModelRegistry
from tests.conftest import failing_prune_claims_of, failing_renames_of
from tests.orchestrator.conftest import small_training_data
from uncertainty.config import TrainConfig

TINY = TrainConfig(members=2, widths=(4, 4, 4), batch_size=8, epochs=1, device="cpu", min_rel_improvement=0,
                   progress=False)


def test_a_retrain_whose_prune_cannot_move_a_folder_aside_warns_of_it(tmp_path, monkeypatch, caplog):
    data = tmp_path / "data"
    small_training_data(data)
    stuck = ModelRegistry(data).models_dir / "m000009-0badf00d"  # as a register killed before its commit leaves it
    stuck.mkdir()
    (stuck / "weights.pt").write_bytes(b"a killed register's")
    failing_renames_of(monkeypatch, lambda src: src == stuck, errno.ENOSPC)

    with caplog.at_level(logging.WARNING, logger="orchestrator.retrain"):
        result = run_retrain(data, TINY, keep_models=1)

    line = ("checkpoint folder models/m000009-0badf00d (no model row names it: a register killed before its commit) "
            "could not be moved aside to models/.orphans/ (No space left on device); it stays where it is, unused, "
            "until a later prune or sweep")
    assert result["prune_error"] is None and result["warnings"][-1:] == [line]
    assert [r.getMessage() for r in caplog.records if r.name == "orchestrator.retrain"] == [line]
    assert (stuck / "weights.pt").read_bytes() == b"a killed register's"
    assert ModelRegistry(data).champion() == result["champion"] == result["version"]


def test_a_retrain_whose_prune_cannot_delete_a_model_warns_of_it_and_keeps_it_usable(tmp_path, monkeypatch):
    data = tmp_path / "data"
    small_training_data(data)
    first = run_retrain(data, TINY)["version"]
    models = ModelRegistry(data).models_dir  # (the claim of a model's folder, not a register's .tmp-* rename)
    failing_prune_claims_of(monkeypatch, lambda src: src.parent == models and not src.name.startswith("."))

    result = run_retrain(data, TINY, keep_models=1)

    out = result["version"] if result["champion"] == first else first  # whichever the gate left out of service
    assert result["prune_error"] is None and result["pruned"] == []
    assert result["warnings"][-1] == (f"the prune could not delete the files of {out} (cannot delete {out}/: "
                                      "Permission denied); a model still whole stays unpruned and usable")
    assert ModelRegistry(data).get(out).pruned_at is None and ModelRegistry(data).load_weights(out)
