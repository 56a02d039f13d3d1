import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from storage.errors import CorruptCheckpointError, RegistryError
from storage.models import ModelRegistry
from storage.records import MAX_FRAME_SIZE, MIN_TRAINABLE_SIZE, trainable_size
from uncertainty.checkpoint import ensemble_from_bytes, ensemble_to_bytes, load_ensemble, save_candidate
from uncertainty.ensemble import Ensemble
from uncertainty.errors import CheckpointError, ConfigError
from uncertainty.metrics import SSIM_WINDOW
from uncertainty.model import MAX_IMAGE_SIZE, PredictorConfig

CFG = PredictorConfig(image_size=16, widths=(4, 8, 8), action_hidden=8)
METRICS = {"h1_mse": 0.01, "h1_psnr": 20.0}


def _ensemble() -> Ensemble:
    ens = Ensemble(CFG, members=2, seed=3)
    ens.set_action_stats([256.0, 250.0], [100.0, 90.0])
    return ens


def test_round_trip_through_the_registry_gives_the_same_predictions(tmp_path):
    registry = ModelRegistry(tmp_path)
    ens = _ensemble()
    version = save_candidate(registry, ens, METRICS, "snap", "evalhash", train_config={"epochs": 1})
    rec = registry.get(version)
    assert rec.config["predictor"] == CFG.to_dict() and rec.config["members"] == 2
    assert rec.metrics == METRICS and rec.snapshot_id == "snap" and rec.eval_split_hash == "evalhash"
    loaded = load_ensemble(registry, version, device="cpu")
    assert loaded.version == version and not loaded.training
    ctx, act = torch.rand(3, 2, 3, 16, 16), torch.rand(3, 2) * 512
    with torch.no_grad():
        torch.testing.assert_close(loaded(ctx, loaded.normalize_actions(act)), ens(ctx, ens.normalize_actions(act)),
                                   atol=0, rtol=0)
    torch.testing.assert_close(loaded.action_std, ens.action_std)


def test_load_without_version_takes_the_champion(tmp_path):
    registry = ModelRegistry(tmp_path)
    with pytest.raises(RegistryError, match="no champion"):
        load_ensemble(registry)
    version = save_candidate(registry, _ensemble(), METRICS, "snap", "evalhash")
    registry.promote(version)
    assert load_ensemble(registry, device="cpu").version == version


def test_corrupt_weights_on_disk_are_refused(tmp_path):
    registry = ModelRegistry(tmp_path)
    version = save_candidate(registry, _ensemble(), METRICS, "snap", "evalhash")
    path = registry.get(version).weights_path
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptCheckpointError, match="sha256 mismatch"):
        load_ensemble(registry, version)


@pytest.mark.parametrize("weights", [b"not a torch file", b"abcde", b"\x80\x02"], ids=["text", "IndexError", "proto"])
def test_registered_bytes_that_are_not_an_ensemble_are_refused(tmp_path, weights):
    """Whatever torch's unpickler raises on them (b"abcde": an IndexError from its stack) is a CheckpointError."""
    registry = ModelRegistry(tmp_path)
    version = registry.register(weights, {}, METRICS, "snap", "evalhash")
    with pytest.raises(CheckpointError, match="not a readable torch file") as info:
        load_ensemble(registry, version)
    assert isinstance(info.value, CorruptCheckpointError)  # one except clause catches both kinds


@pytest.mark.parametrize("change, message", [
    (lambda p: p.update(format="other"), "format must be"),
    (lambda p: p.update(format_version=99), "format_version"),
    (lambda p: p["params"].pop("enc1.weight"), "parameters must be"),
    (lambda p: p["params"].update({"enc1.weight": torch.zeros(1)}), "shape"),
    (lambda p: p.update(predictor={"image_size": 12}), "config is invalid"),
    (lambda p: p.update(action_std=torch.zeros(2)), "normalisation"),
    (lambda p: p.update(members="x"), "config is invalid"),
    (lambda p: p.update(seed=2 ** 70), "config is invalid"),
    (lambda p: p["predictor"].update(widths="abc"), "config is invalid"),
    (lambda p: p.update(action_mean=torch.tensor([float("nan"), 0.0])), "finite"),
    (lambda p: p["params"]["out.bias"].fill_(float("inf")), "non-finite"),
    (lambda p: p.update(params=[1, 2]), "dict of names to tensors"),
    (lambda p: p["params"].update({"enc1.weight": "x"}), "dict of names to tensors"),
    (lambda p: p["params"].update({1: torch.zeros(1)}), "dict of names to tensors"),  # was a TypeError
    (lambda p: p.update(members=0), "members must be >= 1"),
    (lambda p: p.update(members=3), "does not match its weights"),  # 2 members' tensors
    # Built as claimed, these allocated terabytes or looped for hours before the tensors were compared:
    (lambda p: p["predictor"].update(widths=[200_000] * 3), "does not match its weights"),
    (lambda p: p.update(members=10 ** 7), "does not match its weights"),
    (lambda p: p["predictor"].update(image_size=8 * 10 ** 6), "image_size must be a multiple of 8 in"),
])
def test_inconsistent_checkpoints_are_refused(change, message):
    payload = torch.load(io.BytesIO(ensemble_to_bytes(_ensemble())), weights_only=True)
    change(payload)
    buf = io.BytesIO()
    torch.save(payload, buf)
    with pytest.raises(CheckpointError, match=message):
        ensemble_from_bytes(buf.getvalue())


def test_the_predictors_largest_frame_is_the_catalogs():
    assert MAX_IMAGE_SIZE == MAX_FRAME_SIZE
    PredictorConfig(image_size=MAX_IMAGE_SIZE)
    with pytest.raises(ConfigError, match="image_size"):
        PredictorConfig(image_size=MAX_IMAGE_SIZE + 8)


def test_every_size_storage_calls_trainable_is_one_the_predictor_and_ssim_take():
    """``storage.records.trainable_size`` holds the rule; this package imports nothing of it."""
    sizes = [s for s in range(MAX_FRAME_SIZE + 1) if trainable_size(s)]
    assert sizes[0] == MIN_TRAINABLE_SIZE >= SSIM_WINDOW
    for size in sizes:
        PredictorConfig(image_size=size)


def test_checkpoint_loads_with_weights_only():
    payload = torch.load(io.BytesIO(ensemble_to_bytes(_ensemble())), weights_only=True)
    assert payload["members"] == 2


def test_many_tiny_members_at_a_large_frame_load_without_a_buffer_per_member(tmp_path):
    """Each predictor holds coordinate grids of the frame size (8 MiB at 1024 px): a small file of 300
    tiny members at 1024 px made the ensemble build 300 of them at once (2.5 GB). In a child process
    whose address space is capped at what it has plus 1 GiB, it loads."""
    payload = torch.load(io.BytesIO(ensemble_to_bytes(
        Ensemble(PredictorConfig(image_size=16, widths=(1, 1, 1), action_hidden=1), members=300))), weights_only=True)
    payload["predictor"]["image_size"] = 1024  # the parameters do not depend on it
    path = tmp_path / "ckpt.pt"
    torch.save(payload, path)
    script = (
        "import resource, sys\n"
        "from uncertainty.checkpoint import ensemble_from_bytes\n"
        "with open('/proc/self/statm') as f: vsz = int(f.read().split()[0]) * resource.getpagesize()\n"
        "resource.setrlimit(resource.RLIMIT_AS, (vsz + (1 << 30), resource.RLIM_INFINITY))\n"
        f"ens = ensemble_from_bytes(open({str(path)!r}, 'rb').read(), 'cpu')\n"
        "print('loaded', ens.members)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0 and "loaded 300" in done.stdout, done.stderr[-2000:]
