"""The model commands (``train``, ``eval``, ``score``, ``models``) given what an operator, or a damaged or hand-made
file, should not give them: one line and a non-zero exit, never a traceback, and nothing changed."""

from __future__ import annotations

import io
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from orchestrator.cli import build_parser
from tests.conftest import run_cli
from tests.test_cli_models import _episode, small_catalog
from storage.catalog import Catalog
from storage.models import ModelRegistry
from uncertainty.checkpoint import ensemble_from_bytes, ensemble_to_bytes
from uncertainty.config import MAX_EPOCHS, MAX_SEED, TrainConfig
from uncertainty.ensemble import Ensemble
from uncertainty.errors import CheckpointError, ConfigError
from uncertainty.model import PredictorConfig


@pytest.fixture(scope="module")
def catalog_dir(tmp_path_factory):
    """A data dir with 2 train and 1 pinned eval episode (16x16), no model."""
    return small_catalog(tmp_path_factory.mktemp("hostile") / "data", seed=11, train=2, eval_=1)


@pytest.mark.parametrize("seed", [MAX_SEED + 1, 10**30])
def test_train_with_a_seed_past_64_bits_is_a_usage_error_and_registers_nothing(capsys, catalog_dir, seed) -> None:
    """torch's generators take 64 bits: ``--seed 2**64`` was a ValueError traceback from inside the trainer."""
    rc, out, err = run_cli(capsys, "train", "--data", str(catalog_dir), "--members", "2", "--epochs", "1",
                           "--device", "cpu", "--seed", str(seed))
    assert rc == 2 and out == "" and len(err.strip().splitlines()) == 1, err
    assert f"--seed must be an integer from 0 to {MAX_SEED} (2**64 - 1), found {seed}" in err
    assert ModelRegistry(catalog_dir).list() == []


def test_train_config_takes_every_64_bit_seed() -> None:
    assert TrainConfig(seed=MAX_SEED).seed == MAX_SEED
    with pytest.raises(ConfigError, match="seed must be"):
        TrainConfig(seed=-1)


def _checkpoint(change) -> bytes:
    """A real 16px, 2-member checkpoint's bytes with ``change(payload)`` applied (what a hand-made or foreign
    file may hold: its sha256 is registered with it, so only the loader's checks stand in the way)."""
    payload = torch.load(io.BytesIO(ensemble_to_bytes(Ensemble(PredictorConfig(image_size=16), members=2))),
                         weights_only=True)
    change(payload)
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def _first_param(payload: dict, make) -> None:
    name = next(iter(payload["params"]))
    payload["params"][name] = make(payload["params"][name])


# Each was a traceback (TypeError, NotImplementedError or RuntimeError from torch) out of `eval` and `score`.
HOSTILE = {
    "a context past 64 bits": (lambda p: p["predictor"].update(context=10**30), "makes no predictor"),
    "a width past 64 bits": (lambda p: p["predictor"].update(widths=[16, 32, 10**30]), "makes no predictor"),
    "a float action_dim": (lambda p: p["predictor"].update(action_dim=2.0), "action_dim: expected an integer"),
    "a float context": (lambda p: p["predictor"].update(context=2.0), "context: expected an integer"),
    "a sparse parameter": (lambda p: _first_param(p, lambda t: t.to_sparse()), "dense floating-point tensor"),
    "a meta parameter": (lambda p: _first_param(p, lambda t: torch.empty(t.shape, device="meta")),
                         "dense floating-point tensor"),
    "a sparse action_mean": (lambda p: p.update(action_mean=torch.zeros(2).to_sparse()),
                             "action_mean must be a finite floating-point tensor of shape (2,), found a "
                             "torch.sparse_coo"),
}


@pytest.mark.parametrize("what", list(HOSTILE))
def test_eval_and_score_refuse_a_checkpoint_torch_cannot_build_in_one_line(capsys, tmp_path, what) -> None:
    change, words = HOSTILE[what]
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    version = reg.register(_checkpoint(change), {"members": 2}, {"h1_mse": 0.01}, "snap", "split")
    reg.gate(version)  # the first champion
    episode = Catalog(data).add_episode(_episode(np.random.default_rng(2))).episode_id
    for argv in (("eval", version[:7]), ("eval",), ("score", episode)):
        rc, out, err = run_cli(capsys, *argv, "--data", str(data), "--device", "cpu")
        assert rc == 1 and out == "" and len(err.strip().splitlines()) == 1, (argv, err)
        assert "cannot load" in err and "checkpoint" in err and words in err, (argv, err)
    assert reg.champion() == version


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.complex64])
def test_a_checkpoint_of_integer_or_complex_weights_is_refused_not_cast(dtype) -> None:
    """``copy_`` would cast them into the float parameters without a word (complex: with a warning)."""
    data = _checkpoint(lambda p: _first_param(p, lambda t: t.to(dtype)))
    with pytest.raises(CheckpointError, match=f"must be a dense floating-point tensor, found a torch.strided {dtype}"):
        ensemble_from_bytes(data, "cpu")


def test_a_whole_checkpoint_still_loads() -> None:
    ensemble = ensemble_from_bytes(_checkpoint(lambda p: None), "cpu")
    assert ensemble.members == 2 and ensemble.config.image_size == 16


def _read_only_mount_works() -> bool:
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True) if shutil.which("unshare") else None
    return probe is not None and probe.returncode == 0


@pytest.mark.skipif(not _read_only_mount_works(), reason="needs unshare -m (root) for a real read-only bind mount")
@pytest.mark.parametrize("argv", [("models", "ls"), ("eval",), ("score", "0")])
def test_a_read_only_data_directory_is_named_as_such_in_one_line(tmp_path, argv) -> None:
    """SQLite said only 'unable to open database file' of a data directory on a read-only mount."""
    data = tmp_path / "data"
    Catalog(data).add_episode(_episode(np.random.default_rng(5)))
    ModelRegistry(data)
    before = sorted((p.name, p.stat().st_size) for p in data.iterdir())
    cli = " ".join(shlex.quote(a) for a in (sys.executable, "-m", "orchestrator", *argv, "--data", str(data)))
    script = (f"mount --bind {shlex.quote(str(data))} {shlex.quote(str(data))} && "
              f"mount -o remount,ro,bind {shlex.quote(str(data))} || exit 99; exec {cli}")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).parents[1])
    if proc.returncode == 99:
        pytest.skip(f"no read-only bind mount here: {proc.stderr.strip()}")
    assert proc.returncode == 1 and proc.stdout == "" and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert f"({data} cannot be written: SQLite writes its -wal and -shm files beside the database" in proc.stderr
    assert sorted((p.name, p.stat().st_size) for p in data.iterdir()) == before


def test_score_of_an_episode_of_another_frame_size_than_the_champion_says_both_sizes(capsys, tmp_path) -> None:
    """It said ``frames must be (T,16,16,3), found (12, 24, 24, 3)``: the arrays, not what differs or why."""
    from storage.episodes import encode_episode
    data = tmp_path / "data"
    reg = ModelRegistry(data)
    reg.gate(reg.register(_checkpoint(lambda p: None), {"members": 2}, {"h1_mse": 0.01}, "snap", "split"))
    episode = _episode(np.random.default_rng(3), size=24)
    path = tmp_path / "other.mcap"
    path.write_bytes(encode_episode(episode))
    rc, out, err = run_cli(capsys, "score", str(path), "--data", str(data), "--device", "cpu")
    assert rc == 1 and out == "" and len(err.strip().splitlines()) == 1, err
    assert f"episode {episode.meta.episode_id}: its frames are 24px, the champion's 16px" in err, err


@pytest.mark.parametrize("command", [["train"], ["retrain"], ["bench", "loop"]])
@pytest.mark.parametrize("epochs", [str(10**20), str(MAX_EPOCHS + 1)])
def test_epochs_past_the_cap_are_refused_when_parsed(capsys, tmp_path, command, epochs) -> None:
    """``--epochs 10**20`` was taken, and trained until Ctrl-C (parsed only: the old code would train)."""
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args([*command, "--epochs", epochs, "--data", str(tmp_path / "d")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1, err
    assert f"argument --epochs: expected at most {MAX_EPOCHS} epochs, found {epochs}" in err
    assert build_parser().parse_args([*command, "--epochs", str(MAX_EPOCHS)]).epochs == MAX_EPOCHS


def test_run_refuses_retrain_args_of_too_many_epochs(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["run", "--retrain-args", f"--epochs {10**20}"])
    assert stop.value.code == 2 and f"expected at most {MAX_EPOCHS} epochs" in capsys.readouterr().err


def test_train_config_refuses_too_many_epochs() -> None:
    assert TrainConfig(epochs=MAX_EPOCHS).epochs == MAX_EPOCHS
    with pytest.raises(ConfigError, match=f"epochs must be <= {MAX_EPOCHS}, found {MAX_EPOCHS + 1}"):
        TrainConfig(epochs=MAX_EPOCHS + 1)


@pytest.mark.parametrize("argv", [("train", "--members", "2", "--epochs", "1", "--device", "cpu"), ("models", "ls"),
                                  ("eval", "--device", "cpu"), ("score", "ID", "--device", "cpu")])
def test_a_file_where_the_models_folder_goes_is_named_in_one_line(capsys, tmp_path, argv) -> None:
    """Every model command said only "[Errno 17] File exists: '.../models'"."""
    data = small_catalog(tmp_path / "data", seed=3, train=1, eval_=1)
    (data / "models").write_text("not a folder")
    episode = Catalog(data).list()[0].episode_id
    rc, out, err = run_cli(capsys, *(episode if a == "ID" else a for a in argv), "--data", str(data))
    assert rc == 1 and out == "" and err.count("\n") == 1, err
    assert f"{data / 'models'} is not a directory: the registry keeps its checkpoints there; move the file away" \
        in err
    assert (data / "models").read_text() == "not a folder"


def test_a_dangling_link_where_the_models_folder_goes_is_named_as_a_link(capsys, tmp_path) -> None:
    """``DATA/models`` a link to a volume not mounted: not a file to move away."""
    data = small_catalog(tmp_path / "data", seed=3, train=1, eval_=1)
    (data / "models").symlink_to(tmp_path / "volume")
    rc, out, err = run_cli(capsys, "models", "ls", "--data", str(data))
    assert rc == 1 and out == "" and err.count("\n") == 1, err
    assert f"{data / 'models'} is a link to {tmp_path / 'volume'}, which is not a directory (a volume not mounted?): " \
        "the registry keeps its checkpoints there; mount it, or point the link at the folder" in err
    assert (data / "models").is_symlink() and not (tmp_path / "volume").exists()
