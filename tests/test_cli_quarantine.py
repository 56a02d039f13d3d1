"""The ``episodes quarantine`` and ``episodes restore`` commands, in-process (split from test_cli_collect.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from storage.catalog import Catalog
from tests.conftest import run_cli
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(5)


def test_quarantine_restore_and_verify_quarantine(capsys, data_dir, rng, tmp_path):
    cat = Catalog(data_dir)
    eps = [make_episode(rng) for _ in range(3)]
    for ep in eps:
        cat.add_episode(ep)
    ids = [e.meta.episode_id for e in eps]
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(cat.get(ids[2]).path.read_bytes())

    rc, out, err = run_cli(capsys, "episodes", "quarantine", ids[0][:10], "--reason", "blurred frames",
                           "--data", str(data_dir))
    assert rc == 0 and f"quarantined {ids[0]}: blurred frames" in out, err
    rc, out, err = run_cli(capsys, "episodes", "quarantine", ids[0], "--reason", "again", "--data", str(data_dir))
    assert rc == 0 and out == f"already quarantined (the first reason stays) {ids[0]}: blurred frames\n", err
    rc, out, _ = run_cli(capsys, "episodes", "ls", "--quarantined", "--data", str(data_dir))
    assert rc == 0 and ids[0] in out and ids[1] not in out and "quarantined: blurred frames" in out
    assert "1 of 3 episodes (1 quarantined)" in out
    rc, out, _ = run_cli(capsys, "episodes", "show", ids[0], "--data", str(data_dir), "--json")
    assert json.loads(out)["quarantined"] == "blurred frames"

    cat.get(ids[1]).path.unlink()
    cat.get(ids[2]).path.write_bytes(b"\x89MCAP0\r\n")
    rc, out, _ = run_cli(capsys, "episodes", "verify", "--data", str(data_dir))
    # (the quarantined one is not checked)
    assert rc == 1 and "verified 2 episodes: 0 ok, 2 bad; 1 quarantined in all" in out
    rc, out, err = run_cli(capsys, "episodes", "verify", "--quarantine", "--data", str(data_dir), "--json")
    report = json.loads(out)
    assert rc == 0, err
    assert report["bad"] == 2 and all(r["quarantined"] for r in report["episodes"]) and report["quarantined"] == 3
    assert cat.snapshot().ids == []

    rc, out, err = run_cli(capsys, "episodes", "restore", ids[0], ids[1], "--data", str(data_dir))
    assert rc == 1 and f"restored {ids[0]}" in out
    assert f"cannot restore episode {ids[1]}: its file was already missing when it was quarantined" in err
    rc, out, _ = run_cli(capsys, "ingest", str(copy), "--data", str(data_dir), "--json")  # the bytes bring it back
    assert rc == 0 and json.loads(out)["files"][0]["restored"] is True
    assert sorted(cat.snapshot().ids) == sorted([ids[0], ids[2]])


@pytest.mark.parametrize("argv,needle", [
    (["episodes", "quarantine", "nope", "--reason", "x"], "no episode 'nope'"),
    (["episodes", "quarantine", "ID", "--reason", "  "], "--reason must say why"),
    (["episodes", "quarantine", "ID"], "the following arguments are required: --reason"),
    (["episodes", "restore", "nope"], "no episode 'nope'"),
])
def test_quarantine_usage_errors_change_nothing(capsys, data_dir, rng, argv, needle):
    ep = make_episode(rng)
    Catalog(data_dir).add_episode(ep)
    argv = [ep.meta.episode_id if a == "ID" else a for a in argv]
    rc, _, err = run_cli(capsys, *argv, "--data", str(data_dir))
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1
    assert Catalog(data_dir).count(quarantined=True) == 0


def test_restore_all_and_its_usage(capsys, data_dir, rng):
    cat = Catalog(data_dir)
    ids = [cat.add_episode(make_episode(rng)).episode_id for _ in range(3)]
    for i in ids[:2]:
        cat.quarantine(i, "found by a training job: the disk was away")
    for argv in ((), (ids[0], "--all")):
        rc, _, err = run_cli(capsys, "episodes", "restore", *argv, "--data", str(data_dir))
        assert rc == 2 and "give the episodes to restore, or --all (not both)" in err
    rc, out, _ = run_cli(capsys, "episodes", "restore", "--all", "--data", str(data_dir), "--json")
    assert rc == 0 and [r["episode_id"] for r in json.loads(out)] == ids[:2]
    assert cat.count(quarantined=True) == 0 and len(cat.snapshot().ids) == 3
    rc, out, err = run_cli(capsys, "episodes", "restore", "--all", "--data", str(data_dir))
    assert rc == 0 and out == f"nothing is quarantined in {cat.data_dir}\n" and err == ""
    rc, out, _ = run_cli(capsys, "episodes", "restore", "--all", "--data", str(data_dir), "--json")
    assert rc == 0 and json.loads(out) == []


def test_restore_refusals_are_one_line_whatever_the_path(capsys, rng, tmp_path):
    data = tmp_path / "nl\nX"
    cat = Catalog(data)
    row = cat.quarantine(cat.add_episode(make_episode(rng)).episode_id, "suspect")
    kept = data / "quarantine" / row.path.parent.name / row.path.name
    kept.write_bytes(b"damaged since")
    rc, _, err = run_cli(capsys, "episodes", "restore", row.episode_id, "--data", str(data))
    assert rc == 1 and err.count("\n") == 1 and "nl\\nX" in err, err


def test_quarantining_a_pinned_eval_episode_is_a_usage_error_and_changes_nothing(capsys, data_dir, rng):
    cat = Catalog(data_dir)
    train = cat.add_episode(make_episode(rng)).episode_id
    pinned = cat.add_episode(make_episode(rng), split="eval").episode_id
    cat.pin_eval_split([pinned])
    rc, out, err = run_cli(capsys, "episodes", "quarantine", train, pinned[:10], "--reason", "x",
                           "--data", str(data_dir))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"{pinned} is in the pinned eval split, which cannot change" in err and "ingest its bytes" in err
    assert cat.count(quarantined=True) == 0  # not the train episode named before it either


def test_restoring_an_episode_in_training_is_a_no_op_that_says_so(capsys, data_dir, rng):
    """As ``quarantine`` of a quarantined episode is (exit 0): ``restore`` of one in training was an error, exit 1."""
    cat = Catalog(data_dir)
    ids = [cat.add_episode(make_episode(rng)).episode_id for _ in range(2)]
    cat.quarantine(ids[1], "suspect")
    before = cat.get(ids[0]).path.read_bytes()
    rc, out, err = run_cli(capsys, "episodes", "restore", ids[0], ids[1], "--data", str(data_dir))
    assert (rc, err) == (0, ""), err
    assert out == f"not quarantined (already in training) {ids[0]}\nrestored {ids[1]}\n"
    rc, out, err = run_cli(capsys, "episodes", "restore", ids[1], "--data", str(data_dir), "--json")
    assert (rc, err) == (0, "") and json.loads(out) == [{"episode_id": ids[1], "ok": True, "quarantined": ""}]
    assert cat.count(quarantined=True) == 0 and sorted(cat.snapshot().ids) == sorted(ids)
    assert cat.get(ids[0]).path.read_bytes() == before
