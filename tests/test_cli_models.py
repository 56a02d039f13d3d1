"""The ``models`` CLI group (and train/eval/score/bench score when uncertainty's code exists)."""

from __future__ import annotations

import errno
import json
import math
import shutil
import subprocess
import sys

import uuid
from pathlib import Path

import numpy as np
import pytest

from orchestrator.cli import main
from orchestrator.retrainlock import EXIT_BUSY, retrain_lock
from tests.conftest import failing_prune_claims_of, failing_renames_of, run_cli
from storage.catalog import Catalog
from storage.models import ModelRegistry, ModelStatus
from storage.records import Episode, EpisodeMeta

SPLIT = "split-aaaa"


@pytest.fixture
def data(tmp_path):
    return tmp_path / "data"


@pytest.fixture
def reg(data) -> ModelRegistry:
    return ModelRegistry(data)


def _register(reg: ModelRegistry, h1_mse: float, split: str = SPLIT) -> str:
    return reg.register(f"w{h1_mse}{split}".encode(), {"members": 2},
                        {"h1_mse": h1_mse, "h1_psnr": 21.5}, "snap", split)


def test_models_ls_json_and_text(capsys, data, reg) -> None:
    rc, out, _ = run_cli(capsys, "models", "ls", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out) == {"champion": None, "champion_problem": None, "models": []}
    a, b, nan = _register(reg, 0.01), _register(reg, 0.5), _register(reg, math.nan)
    reg.gate(a)
    reg.gate(b)
    reg.gate(nan)
    rc, out, _ = run_cli(capsys, "models", "ls", "--data", str(data), "--json")
    listing = json.loads(out)  # strict JSON: NaN became null
    assert rc == 0 and listing["champion"] == a
    assert [(m["version"], m["status"]) for m in listing["models"]] == [
        (a, "champion"), (b, "rejected"), (nan, "rejected")]
    assert listing["models"][2]["metrics"]["h1_mse"] is None
    assert "not better enough" in listing["models"][1]["reason"]
    rc, out, err = run_cli(capsys, "models", "ls", "--data", str(data))
    assert rc == 0 and f"* {a}" in out and "rejected" in out and err == ""
    reg.get(a).weights_path.write_bytes(b"overwritten")  # the champion's weights damaged on disk
    rc, out, err = run_cli(capsys, "models", "ls", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["champion_problem"].startswith(f"checkpoint {a}: weights sha256 mismatch")
    assert "warning: the champion cannot be served: " in err and "models rollback" not in err
    assert "`activecollect models promote VERSION` serves another model (there is no earlier champion" in err
    reg.promote(b)  # an earlier champion now: a rollback is the way back when this one's weights go too
    reg.get(b).weights_path.write_bytes(b"overwritten")
    rc, out, err = run_cli(capsys, "models", "ls", "--data", str(data), "--json")
    assert rc == 0 and "cannot be served" in err and "`activecollect models rollback` returns to the previous" in err


def test_models_show(capsys, data, reg) -> None:
    a = _register(reg, 0.01)
    reg.gate(a)
    rc, out, _ = run_cli(capsys, "models", "show", a, "--data", str(data), "--json")
    shown = json.loads(out)
    assert rc == 0 and shown["version"] == a and shown["status"] == "champion"
    assert shown["eval_split_hash"] == SPLIT and len(shown["champion_history"]) == 1
    rc, out, _ = run_cli(capsys, "models", "show", a, "--data", str(data))
    assert rc == 0 and "h1_mse" in out and SPLIT in out


def test_models_show_promote_and_eval_take_a_unique_prefix(capsys, data, reg) -> None:
    a, b = _register(reg, 0.01), _register(reg, 0.5)  # m000001-..., m000002-...
    reg.gate(a)
    rc, out, err = run_cli(capsys, "models", "show", a.split("-")[0], "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["version"] == a, err
    rc, out, err = run_cli(capsys, "models", "promote", b[:9], "--data", str(data))
    assert rc == 0 and out == f"champion is now {b} (was {a})\n" and reg.champion() == b, err
    for prefix in ("m", "m00000"):  # ambiguous: both named, nothing changed
        rc, out, err = run_cli(capsys, "models", "promote", prefix, "--data", str(data))
        assert rc == 2 and out == "" and err.count("\n") == 1, err
        assert f"model version prefix {prefix!r} is ambiguous ({a}, {b})" in err
    assert reg.champion() == b
    rc, _, err = run_cli(capsys, "models", "show", "M000001", "--data", str(data))  # case counts
    assert rc == 2 and "unknown model version 'M000001'" in err
    rc, _, err = run_cli(capsys, "eval", "m000003", "--data", str(data))
    assert rc == 2 and "unknown model version 'm000003'" in err


def test_models_promote_and_rollback(capsys, data, reg) -> None:
    a, b = _register(reg, 0.01), _register(reg, 0.5)
    reg.gate(a)
    rc, out, _ = run_cli(capsys, "models", "promote", b, "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["promoted"] is True and reg.champion() == b
    rc, out, _ = run_cli(capsys, "models", "rollback", "--data", str(data))
    assert rc == 0 and f"champion is now {a}" in out and reg.champion() == a
    rc, _, err = run_cli(capsys, "models", "rollback", "--data", str(data))
    assert rc == 1 and "no previous champion" in err and len(err.strip().splitlines()) == 1


def test_models_promote_refuses_corrupt_and_wrong_split(capsys, data, reg) -> None:
    a, other = _register(reg, 0.01), _register(reg, 0.001, split="split-bbbb")
    reg.gate(a)
    rc, _, err = run_cli(capsys, "models", "promote", other, "--data", str(data))
    assert rc == 1 and "evaluated on eval split split-bbbb" in err
    b = _register(reg, 0.005)
    path = reg.get(b).weights_path
    path.write_bytes(path.read_bytes()[:-1] + b"X")
    rc, _, err = run_cli(capsys, "models", "promote", b, "--data", str(data))
    assert rc == 1 and "refusing to promote" in err and "sha256 mismatch" in err
    assert reg.champion() == a and reg.get(b).status is ModelStatus.CANDIDATE


def test_models_prune_dry_run_then_prune(capsys, data, reg) -> None:
    a, b, c = _register(reg, 0.01), _register(reg, 0.008), _register(reg, 0.006)
    for v in (a, b, c):
        reg.gate(v)
    worse = _register(reg, 0.5)
    reg.gate(worse)
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "2", "--dry-run", "--data", str(data))
    assert rc == 0 and "would delete 2 models" in out and a in out and worse in out
    assert reg.get(a).weights_path.exists()
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "2", "--data", str(data), "--json")
    result = json.loads(out)
    assert rc == 0 and result["pruned"] == [a, worse] and result["kept"] == [c, b] and result["freed_bytes"] > 0
    assert not reg.get(a).path.exists() and reg.get(b).weights_path.exists()
    rc, out, _ = run_cli(capsys, "models", "ls", "--data", str(data))
    assert rc == 0 and "retired (pruned)" in out and "rejected (pruned)" in out
    rc, out, _ = run_cli(capsys, "models", "show", a, "--data", str(data))
    assert rc == 0 and "weights          pruned at" in out
    rc, _, err = run_cli(capsys, "models", "promote", a, "--data", str(data))
    assert rc == 1 and "refusing to promote" in err and "weights pruned" in err
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "2", "--data", str(data))
    assert rc == 0 and "nothing to delete" in out


def test_models_prune_names_the_folders_it_moves_aside(capsys, data, reg) -> None:
    """A folder no row names (what a register killed before its commit leaves) is moved aside, and said so."""
    a = _register(reg, 0.01)
    reg.gate(a)
    shutil.copytree(reg.get(a).path, reg.models_dir / "m000009-0badf00d")
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--dry-run", "--data", str(data))
    assert rc == 0 and "would move 1 checkpoint folder(s) no model row names" in out and "m000009-0badf00d" in out
    assert (reg.models_dir / "m000009-0badf00d").is_dir()
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data))
    assert rc == 0 and out.startswith("nothing to delete") and "moved 1 checkpoint folder(s)" in out
    assert "to models/.orphans/" in out
    assert (reg.models_dir / ".orphans" / "m000009-0badf00d").is_dir()
    assert not (reg.models_dir / "m000009-0badf00d").exists()


def test_models_prune_frees_all_the_same_when_a_folder_cannot_be_moved_aside(capsys, monkeypatch, data, reg) -> None:
    """A full disk: the folder no row names cannot be moved aside; the prune deletes what it should (exit 0), says
    which folder stayed and why, and --json has it under not_moved."""
    a, b = _register(reg, 0.01), _register(reg, 0.008)
    reg.gate(a)
    reg.gate(b)
    shutil.copytree(reg.get(b).path, reg.models_dir / "m000009-0badf00d")
    failing_renames_of(monkeypatch, lambda src: src.name == "m000009-0badf00d", errno.ENOSPC)
    rc, out, err = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data))
    assert rc == 0 and err == "" and out.startswith("deleted 1 model's files") and a in out
    assert ("could not move 1 checkpoint folder(s) no model row names to models/.orphans/, left where they are "
            "(unused; the next prune tries again): m000009-0badf00d (No space left on device)") in out
    assert not reg.get(a).path.exists() and (reg.models_dir / "m000009-0badf00d").is_dir()
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data), "--json")
    result = json.loads(out)
    assert rc == 0 and result["not_moved"] == {"m000009-0badf00d": "No space left on device"}
    assert result["orphaned"] == []
    monkeypatch.undo()
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["orphaned"] == ["m000009-0badf00d"] and json.loads(out)["not_moved"] == {}


@pytest.mark.parametrize("argv, words", [
    (("models",), "required"),
    (("models", "frobnicate"), "invalid choice"),
    (("models", "show"), "VERSION"),
    (("models", "show", "m999999-deadbeef"), "unknown model version"),
    (("models", "promote", "nope"), "unknown model version"),
    (("models", "prune"), "--keep"),
    (("models", "prune", "--keep", "0"), "positive integer"),
])
def test_models_usage_errors_exit_2(capsys, data, reg, argv, words) -> None:
    rc, out, err = run_cli(capsys, *argv, *(("--data", str(data)) if len(argv) > 2 else ()))
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1 and out == ""


def test_missing_data_dir_is_a_usage_error(capsys, tmp_path) -> None:
    rc, _, err = run_cli(capsys, "models", "ls", "--data", str(tmp_path / "nowhere"))
    assert rc == 2 and "no data directory" in err
    assert not (tmp_path / "nowhere").exists()


def test_entry_point_exits_2_in_one_line(tmp_path) -> None:
    proc = subprocess.run([sys.executable, "-m", "orchestrator", "models", "show"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


# -- train / eval / score / bench score on a tiny synthetic catalog (16x16, 2 members, 1 epoch) --------


def _episode(rng: np.random.Generator, steps: int = 12, size: int = 16) -> Episode:
    """A square pushed around a 16x16 frame: real frames, actions and states, made without the sim."""
    pos = rng.uniform(100, 400, size=2)
    frames = np.zeros((steps, size, size, 3), np.uint8)
    actions = rng.uniform(0, 512, size=(steps, 2)).astype(np.float32)
    states = np.zeros((steps, 11))
    for t in range(steps):
        x, y = (pos / 512 * (size - 4)).astype(int)
        frames[t, y:y + 4, x:x + 4] = (200, 60, 30)
        states[t, 4:6] = pos
        pos = pos + 0.2 * (actions[t] - pos)
    meta = EpisodeMeta(episode_id=uuid.UUID(bytes=rng.bytes(16)).hex, task="push", shape="box",
                       physics={"mass": 1.0, "friction": 0.5, "ground_friction": 0.3}, seed=int(rng.integers(2**31)),
                       policy="random_waypoints", image_size=size, created="2026-01-01T00:00:00+00:00")
    return Episode(meta, frames, actions, states)


def small_catalog(data: Path, seed: int, train: int, eval_: int) -> Path:
    """``data`` with a catalog of ``train`` 16 px train episodes and a pinned eval split of ``eval_``."""
    catalog, rng = Catalog(data), np.random.default_rng(seed)
    for _ in range(train):
        catalog.add_episode(_episode(rng), split="train")
    catalog.pin_eval_split([catalog.add_episode(_episode(rng), split="eval").episode_id for _ in range(eval_)])
    return data


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A data dir with 6 train and 2 pinned eval episodes, and one ``train`` run's JSON output."""
    data = small_catalog(tmp_path_factory.mktemp("trained") / "data", seed=7, train=6, eval_=2)
    rc = main(["train", "--data", str(data), "--members", "2", "--epochs", "1", "--device", "cpu", "--json"])
    return data, rc


def test_train_registers_and_promotes_the_first_model(trained, capsys) -> None:
    data, rc = trained
    assert rc == 0
    reg = ModelRegistry(data)
    (first,) = reg.list()
    assert reg.champion() == first.version and first.status is ModelStatus.CHAMPION
    assert first.eval_split_hash == Catalog(data).eval_split().hash
    assert math.isfinite(first.metrics["h1_mse"])


def test_models_show_episodes_lists_what_the_model_was_trained_on(trained, capsys, tmp_path) -> None:
    data, _ = trained
    version = ModelRegistry(data).list()[0].version
    train_ids = Catalog(data).snapshot().ids
    rc, out, err = run_cli(capsys, "models", "show", version, "--data", str(data), "--episodes")
    assert rc == 0 and out.split() == train_ids and err == ""
    rc, out, _ = run_cli(capsys, "models", "show", version, "--data", str(data), "--episodes", "--json")
    shown = json.loads(out)
    assert rc == 0 and shown["snapshot_episode_count"] == 6
    assert [e["episode_id"] for e in shown["snapshot_episodes"]] == train_ids
    rc, out, _ = run_cli(capsys, "models", "show", version, "--data", str(data))
    assert rc == 0 and f"data snapshot    {shown['snapshot_id']}: 6 episodes (--episodes lists them)" in out
    copy = tmp_path / "copy"  # a model registered without its episodes (an older trainer), and a damaged file
    shutil.copytree(data, copy)
    snapshot_file = ModelRegistry(copy).get(version).path / "snapshot.json"
    snapshot_file.unlink()
    rc, out, err = run_cli(capsys, "models", "show", version, "--data", str(copy), "--episodes")
    assert rc == 1 and out == "" and f"cannot list the episodes of {version}: episodes not recorded" in err
    assert f"no snapshot.json in {snapshot_file.parent} (registered before models recorded them, or the file was " \
           "removed)" in err
    rc, out, _ = run_cli(capsys, "models", "show", version, "--data", str(copy), "--json")
    assert rc == 0 and json.loads(out)["snapshot_episode_count"] is None
    snapshot_file.write_text('{"episodes": [["a", "b"]]}')
    rc, out, _ = run_cli(capsys, "models", "show", version, "--data", str(copy))
    assert rc == 0 and "episodes unavailable: checkpoint" in out and "are not its snapshot" in out


def test_train_json_and_warm_start(trained, capsys) -> None:
    data, _ = trained
    champion = ModelRegistry(data).champion()
    rc, out, _ = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1",
                      "--device", "cpu", "--from-champion", "--seed", "3", "--json")
    result = json.loads(out)
    assert rc == 0 and set(result) >= {"version", "metrics", "decision", "champion"}
    assert ModelRegistry(data).get(result["version"]).parent == champion
    assert isinstance(result["decision"]["promoted"], bool) and result["decision"]["reason"]


def test_train_waits_its_turn_and_rejects_what_a_dead_job_left(trained, capsys, tmp_path) -> None:
    from orchestrator.retrain import ABANDONED, abandoned_note
    data = tmp_path / "copy"
    shutil.copytree(trained[0], data)
    reg = ModelRegistry(data)
    # what a job killed between its register and its gate leaves: a candidate no job will gate
    left = reg.register(b"weights of a job that died", {"members": 2}, {"h1_mse": 1.0}, "snap", SPLIT)
    argv = ("train", "--data", str(data), "--members", "2", "--epochs", "1", "--device", "cpu", "--json")
    with retrain_lock(data):  # a retrain job is running
        rc, out, err = run_cli(capsys, *argv)
    assert rc == EXIT_BUSY and out == "" and "another retrain holds" in err and len(err.strip().splitlines()) == 1
    assert [m.version for m in reg.list()] == [m.version for m in ModelRegistry(trained[0]).list()] + [left]
    assert reg.get(left).status is ModelStatus.CANDIDATE
    rc, out, _ = run_cli(capsys, *argv[:-1])
    assert rc == 0 and abandoned_note([left]) in out.splitlines() and "gate: " in out
    assert (reg.get(left).status, reg.get(left).reason) == (ModelStatus.REJECTED, ABANDONED)
    assert reg.list(status=ModelStatus.CANDIDATE) == []  # its own candidate went through the gate


def test_train_on_an_old_catalog_of_two_frame_sizes_leaves_the_other_size_out_and_says_so(capsys, monkeypatch,
                                                                                          tmp_path) -> None:
    import storage.catalog
    monkeypatch.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)  # a catalog from before it
    data, rng = tmp_path / "data", np.random.default_rng(3)
    catalog = Catalog(data)
    odd = catalog.add_episode(_episode(rng, size=24)).episode_id
    for _ in range(2):
        catalog.add_episode(_episode(rng), split="train")
    catalog.pin_eval_split([catalog.add_episode(_episode(rng), split="eval").episode_id])
    rc, out, _ = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1", "--device", "cpu",
                         "--json")
    result = json.loads(out)
    note = f"left out 1 train episode(s) whose frames are not the eval split's 16px: {odd} (24px)"
    assert rc == 0 and result["metrics"]["train_episodes"] == 2
    assert result["metrics"]["train_other_size_left_out"] == 1
    assert [line for line in result["warnings"] if note in line]  # (and logged: on stderr outside pytest)
    assert odd not in ModelRegistry(data).snapshot(result["version"]).ids


def test_eval_and_score(trained, capsys) -> None:
    data, _ = trained
    rc, out, _ = run_cli(capsys, "eval", "--data", str(data), "--device", "cpu", "--json")
    evaluated = json.loads(out)
    assert rc == 0 and evaluated["version"] == ModelRegistry(data).champion()
    assert evaluated["metrics"]["eval_split_hash"] == Catalog(data).eval_split().hash
    row = Catalog(data).list(split="train")[0]
    rc, out, _ = run_cli(capsys, "score", row.episode_id[:10], "--data", str(data), "--top", "2",
                      "--device", "cpu", "--json")
    scored = json.loads(out)
    assert rc == 0 and scored["episode_id"] == row.episode_id and len(scored["top"]) == 2
    assert len(scored["per_step"]) == row.frames
    rc, out, _ = run_cli(capsys, "score", str(data / row.path), "--data", str(data), "--device", "cpu")
    assert rc == 0 and "mean disagreement" in out and "step" in out


@pytest.mark.parametrize("frames", [1, 2])
def test_score_of_an_episode_too_short_for_the_model_says_there_is_no_step_to_score(trained, capsys, tmp_path,
                                                                                     frames) -> None:
    from storage.episodes import write_episode
    data, _ = trained
    path = tmp_path / "short.mcap"
    write_episode(path, _episode(np.random.default_rng(frames), steps=frames))
    rc, out, err = run_cli(capsys, "score", str(path), "--data", str(data), "--device", "cpu")
    assert rc == 0 and err == "" and "nan" not in out and out.count("\n") == 1, out
    assert (f"no step to score: each needs the model's 2 context frames and 1 more to predict (3 in all), the "
            f"episode has {frames}") in out
    rc, out, _ = run_cli(capsys, "score", str(path), "--data", str(data), "--device", "cpu", "--json")
    scored = json.loads(out)
    assert "NaN" not in out  # strict JSON
    assert rc == 0 and scored["mean"] is None and scored["per_step"] == [None] * frames and scored["top"] == []


def test_eval_score_without_champion_exit_1(capsys, tmp_path) -> None:
    data = tmp_path / "data"
    catalog = Catalog(data)
    ep = catalog.add_episode(_episode(np.random.default_rng(1)))
    for argv in (("eval",), ("score", ep.episode_id)):
        rc, _, err = run_cli(capsys, *argv, "--data", str(data))
        assert rc == 1 and "no champion model yet" in err, err


def test_train_without_data_exit_1(capsys, tmp_path) -> None:
    data = tmp_path / "data"
    Catalog(data)
    rc, _, err = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1")
    assert rc == 1 and "training failed" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, words", [
    (("train", "--members", "0"), "expected an ensemble of at least 2 members (one cannot disagree), found 0"),
    (("train", "--epochs", "x"), "positive integer"),
    (("train", "--min-improvement", "2"), "argument --min-improvement: expected a fraction in [0, 1)"),
    (("score",), "EPISODE"),
    (("score", "nope-episode"), "no episode"),
    (("score", "missing.mcap"), "no episode file"),
    (("score", "e1", "--top", "-1"), "positive integer"),
    (("score", "e1", "--top", "0"), "positive integer"),
    (("eval", "m999999-deadbeef"), "unknown model version"),
    (("bench", "score", "--seconds", "0"), "positive number"),
    (("bench", "score", "--size", "12", "--seconds", "0.1"), "multiple of 8"),
    (("bench", "score", "--batch", "0"), "positive integer"),
])
def test_usage_errors_exit_2(capsys, data, reg, argv, words) -> None:
    rc, out, err = run_cli(capsys, *argv, *(("--data", str(data)) if argv[0] != "bench" else ()))
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1, err


def test_bench_score_json(capsys) -> None:
    rc, out, _ = run_cli(capsys, "bench", "score", "--members", "2", "--size", "16", "--seconds", "0.3",
                      "--device", "cpu", "--json")
    figures = json.loads(out)
    assert rc == 0 and figures["fused_fps"] > 0 and figures["loop_fps"] > 0 and figures["speedup"] > 0


def test_bench_score_text_names_the_batch_and_the_arithmetic_ceiling(capsys) -> None:
    rc, out, _ = run_cli(capsys, "bench", "score", "--members", "2", "--size", "16", "--seconds", "0.3",
                         "--batch", "1", "--threads", "1", "--device", "cpu")
    assert rc == 0 and "batch 1," in out and "GFLOP/frame" in out and "wide convolution" in out, out


def test_eval_refuses_a_corrupt_or_foreign_champion(capsys, data, reg) -> None:
    version = _register(reg, 0.01)  # weights that are not a torch checkpoint
    reg.gate(version)
    rc, _, err = run_cli(capsys, "eval", "--data", str(data), "--device", "cpu")
    assert rc == 1 and "cannot load the champion" in err and "checkpoint" in err
    path = reg.get(version).weights_path
    path.write_bytes(b"X" + path.read_bytes()[1:])
    rc, _, err = run_cli(capsys, "eval", version, "--data", str(data), "--device", "cpu")
    assert rc == 1 and "sha256 mismatch" in err and len(err.strip().splitlines()) == 1


def test_train_with_a_variance_head_reports_both_calibrations(trained, capsys, tmp_path) -> None:
    import shutil
    data = tmp_path / "data"
    shutil.copytree(trained[0], data)
    rc, _, err = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1",
                         "--device", "cpu", "--from-champion", "--variance-head")
    assert rc == 1 and "no variance head to warm-start" in err and len(err.strip().splitlines()) == 1
    rc, out, _ = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1",
                         "--device", "cpu", "--variance-head", "--min-improvement", "0")
    assert rc == 0 and " windows, 1 epoch in " in out
    assert "promoted: promoted" not in out and "gate: promoted: h1_mse" not in out  # the verdict once
    assert "spearman(disagreement, error)" in out and "spearman(total predictive variance, error)" in out


@pytest.mark.parametrize("argv", [("models", "ls"), ("models", "show", "m1"), ("eval",), ("score", "e1")])
def test_reading_commands_make_no_catalog_where_there_is_none(capsys, tmp_path, argv) -> None:
    plain = tmp_path / "plain"
    plain.mkdir()
    rc, out, err = run_cli(capsys, *argv, "--data", str(plain))
    assert rc == 2 and "no catalog at" in err and err.count("\n") == 1 and list(plain.iterdir()) == []


def test_eval_text_says_which_horizons_the_eval_episodes_are_too_short_for(capsys) -> None:
    from orchestrator.cli.models import _print_eval

    nan = math.nan
    _print_eval({"h1_mse": 1e-3, "h1_psnr": 30.0, "h1_ssim": 0.9, "baseline_h1_mse": 2e-3, "baseline_h1_psnr": 27.0,
                 "h5_mse": 4e-3, "h5_psnr": 24.0, "h5_ssim": 0.8, "baseline_h5_mse": 5e-3, "baseline_h5_psnr": 23.0,
                 "h10_mse": nan, "h10_psnr": nan, "h10_ssim": nan, "spearman": 0.4, "eval_episodes": 2,
                 "eval_windows": 16})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("eval h1   mse      0.001  psnr  30.00 dB") and "copy-last mse      0.002" in lines[0]
    assert lines[2] == "eval h10  undefined: no eval episode is long enough for horizon 10"


def test_models_prune_that_cannot_delete_a_model_says_so_and_exits_1(capsys, monkeypatch, data, reg) -> None:
    """A read-only ``models/``: the model the prune could not delete is named, with why; it stays unpruned and can
    still be promoted; exit 1 (also with --json, which has it under not_deleted)."""
    a, b = _register(reg, 0.01), _register(reg, 0.008)
    reg.gate(a)
    reg.gate(b)
    failing_prune_claims_of(monkeypatch, lambda src: src == reg.models_dir / a)
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data))
    assert rc == 1 and out.startswith(f"nothing deleted (kept {b}); could not delete 1 model(s)' files: {a} "
                                      f"(cannot delete {a}/: Permission denied) -- those still whole stay unpruned")
    rc, out, _ = run_cli(capsys, "models", "prune", "--keep", "1", "--data", str(data), "--json")
    assert rc == 1 and json.loads(out)["not_deleted"] == {a: f"cannot delete {a}/: Permission denied"}
    rc, out, _ = run_cli(capsys, "models", "promote", a, "--data", str(data))
    assert rc == 0 and reg.champion() == a
