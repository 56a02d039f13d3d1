"""The collect / episodes / ingest / eval-split commands, in-process and through the console script."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage import episodes
from storage.catalog import Catalog
from tests.conftest import free_port, run_cli
from tests.storage.test_episodes import make_episode


@pytest.fixture
def data(tmp_path):
    return tmp_path / "data"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(5)


def test_collect_indexes_episodes_and_says_where(capsys, data):
    rc, out, err = run_cli(capsys, "collect", "--episodes", "2", "--size", "16", "--steps", "4",
                        "--seed", "3", "--data", str(data))
    assert rc == 0, err
    assert f"{data}/episodes" in out and "catalog.sqlite (2 episodes)" in out
    cat = Catalog(data)
    rows = cat.list()
    assert [r.shape for r in rows] == ["T", "box"] and all(r.frames == 4 for r in rows)
    for r in rows:
        ep = cat.load(r.episode_id)
        assert ep.frames.shape == (4, 16, 16, 3) and ep.meta.policy == "push"

    rc, out, _ = run_cli(capsys, "collect", "--episodes", "1", "--shape", "disk", "--policy", "random_waypoints",
                      "--size", "16", "--steps", "3", "--data", str(data), "--json")
    report = json.loads(out)
    assert rc == 0 and report["total_episodes"] == 3 and report["frames"] == 3
    assert cat.get(report["episodes"][0]).shape == "disk"


def test_episodes_ls_show_verify(capsys, data, rng):
    cat = Catalog(data)
    eps = [make_episode(rng, shape=s) for s in ("T", "L")]
    for ep in eps:
        cat.add_episode(ep)
    ids = [e.meta.episode_id for e in eps]

    rc, out, _ = run_cli(capsys, "episodes", "ls", "--data", str(data), "--json")
    assert rc == 0 and [r["episode_id"] for r in json.loads(out)] == ids
    rc, out, _ = run_cli(capsys, "episodes", "ls", "--data", str(data), "--shape", "L")
    assert rc == 0 and ids[1] in out and ids[0] not in out

    rc, out, _ = run_cli(capsys, "episodes", "show", ids[0][:10], "--data", str(data), "--json")
    shown = json.loads(out)
    assert rc == 0 and shown["episode_id"] == ids[0] and shown["meta"]["physics"] == eps[0].meta.physics
    rc, out, _ = run_cli(capsys, "episodes", "show", ids[0][:10], "--data", str(data))
    lines = {line.split(maxsplit=1)[0]: line.split(maxsplit=1)[1] for line in out.splitlines()}
    assert rc == 0 and json.loads(lines["physics"]) == eps[0].meta.physics  # JSON, not a Python repr
    assert json.loads(lines["start_state"]) == eps[0].meta.start_state

    rc, out, _ = run_cli(capsys, "episodes", "verify", "--data", str(data))
    assert rc == 0 and "2 ok, 0 bad" in out

    path = cat.get(ids[1]).path
    blob = bytearray(path.read_bytes())
    blob[len(blob) // 2] ^= 1
    path.write_bytes(bytes(blob))
    rc, out, _ = run_cli(capsys, "episodes", "verify", "--data", str(data), "--json")
    report = json.loads(out)
    assert rc == 1 and report["bad"] == 1
    assert [r["ok"] for r in report["episodes"]] == [True, False]
    assert "sha256" in report["episodes"][1]["error"]
    rc, out, _ = run_cli(capsys, "episodes", "verify", ids[0], "--data", str(data))
    assert rc == 0 and "1 ok, 0 bad" in out


def test_ingest_one_good_one_bad(capsys, data, rng, tmp_path):
    good = tmp_path / "good.mcap"
    episodes.write_episode(good, make_episode(rng))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(good.read_bytes()[:-50])
    rc, out, err = run_cli(capsys, "ingest", str(good), str(bad), "--data", str(data))
    assert rc == 1
    assert "ingested" in out and "1 of 2 files indexed" in out
    assert "refused" in err and "bad.mcap" in err and "without an MCAP footer" in err
    assert Catalog(data).count() == 1
    rc, out, _ = run_cli(capsys, "ingest", str(good), "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["files"][0]["duplicate"] is True


def test_an_ingest_that_refuses_every_file_makes_no_catalog(capsys, data, rng, tmp_path):
    good, bad, odd = tmp_path / "good.mcap", tmp_path / "bad.mcap", tmp_path / "odd.mcap"
    episodes.write_episode(good, make_episode(rng))
    bad.write_bytes(good.read_bytes()[:-50])
    episodes.write_episode(odd, make_episode(rng, size=12))  # a size no model trains on
    rc, out, err = run_cli(capsys, "ingest", str(bad), str(odd), str(tmp_path / "notes.txt"), "--data", str(data))
    assert rc == 2 and "no such file" in err and not data.exists()  # (a usage error before any file is read)
    (tmp_path / "notes.txt").write_text("not an episode")
    rc, out, err = run_cli(capsys, "ingest", str(bad), str(odd), str(tmp_path / "notes.txt"), "--data", str(data))
    assert rc == 1 and "0 of 3 files indexed" in out and "not made" in out
    assert err.count("refused") == 3 and "no model trains on" in err
    assert not data.exists()  # a misspelt --data with bad files leaves nothing behind
    rc, out, err = run_cli(capsys, "ingest", str(bad), str(good), "--data", str(data))
    assert rc == 1 and "1 of 2 files indexed" in out and Catalog(data).count() == 1
    assert f"no catalog at {data}: started a new one (a misspelt --data?" in err  # said, where it was made
    rc, out, err = run_cli(capsys, "ingest", str(good), "--data", str(data))
    assert rc == 0 and "started a new one" not in err  # (an existing catalog: nothing to say)


def test_ingest_refuses_physics_outside_the_task_space(capsys, data, rng, tmp_path):
    ep = make_episode(rng)
    ep.meta.physics = {**ep.meta.physics, "mass": 50.0}  # the planner would ask workers for it
    path = tmp_path / "heavy.mcap"
    episodes.write_episode(path, ep)
    rc, out, err = run_cli(capsys, "ingest", str(path), "--data", str(data))
    assert rc == 1 and "0 of 1 files indexed" in out
    assert f"refused {path}: {path}: physics.mass: expected a finite number in [0.2, 5], found 50.0" in err
    assert Catalog(data).count() == 0


@pytest.mark.parametrize("field,value,needle", [
    ("shape", "zzz<script>", "shape: expected one of T, box, L, disk, found 'zzz<script>'"),
    ("task", "fold", "task: expected one of push, found 'fold'"),
    ("created", "9999-99-99", "created: expected an ISO 8601 time, found '9999-99-99'"),
])
def test_ingest_refuses_metadata_outside_the_task_space(capsys, data, rng, tmp_path, field, value, needle):
    ep = make_episode(rng)
    setattr(ep.meta, field, value)
    path = tmp_path / "odd.mcap"
    episodes.write_episode(path, ep)
    rc, out, err = run_cli(capsys, "ingest", str(path), "--data", str(data))
    assert rc == 1 and "0 of 1 files indexed" in out and needle in err, err
    assert Catalog(data).count() == 0


def test_ingest_directory_and_split(capsys, data, rng, tmp_path):
    src = tmp_path / "src"
    for i in range(2):
        episodes.write_episode(src / f"ep{i}.mcap", make_episode(rng))
    (src / ".ep9.mcap.x.tmp").write_bytes(b"leftover")
    rc, out, err = run_cli(capsys, "ingest", str(src), "--split", "eval", "--data", str(data))
    assert rc == 0, err
    assert Catalog(data).count(split="eval") == 2
    rc, out, err = run_cli(capsys, "ingest", str(src / "ep0.mcap"), "--data", str(data))  # (--split train)
    assert rc == 1 and "is already indexed in split 'eval', not 'train' (give --split eval)" in err, err


def test_episodes_ingested_as_eval_are_pinned_by_eval_split_pin(capsys, data, rng, tmp_path):
    src, other = tmp_path / "src", tmp_path / "other"
    for i in range(3):
        episodes.write_episode(src / f"ep{i}.mcap", make_episode(rng))
    episodes.write_episode(other / "train.mcap", make_episode(rng))
    assert run_cli(capsys, "ingest", str(other), "--data", str(data))[0] == 0  # a train episode
    rc, _, err = run_cli(capsys, "eval-split", "pin", "--data", str(data))
    assert rc == 2 and err.count("\n") == 1 and "no eval episodes to pin" in err and "--split eval" in err
    assert run_cli(capsys, "ingest", str(src), "--split", "eval", "--data", str(data))[0] == 0
    rc, _, err = run_cli(capsys, "eval-split", "show", "--data", str(data))
    assert rc == 1 and "3 eval episodes are indexed, not pinned" in err
    assert "pin episodes ingested with --split eval with activecollect eval-split pin" in err
    cat = Catalog(data)
    evals, train = sorted(cat.snapshot("eval").ids), cat.snapshot("train").ids
    rc, _, err = run_cli(capsys, "eval-split", "pin", evals[0], train[0][:12], "--data", str(data))
    assert rc == 1 and "split 'train'" in err and cat.eval_split() is None  # changes nothing
    rc, out, err = run_cli(capsys, "eval-split", "pin", evals[0], evals[1][:12], "--data", str(data), "--json")
    assert rc == 0, err
    pinned = json.loads(out)
    split = cat.eval_split()
    assert split.ids == evals[:2] and pinned == {"hash": split.hash, "episodes": 2}
    assert split.params["image_size"] == cat.frame_size()
    assert run_cli(capsys, "eval-split", "pin", evals[1], evals[0], "--data", str(data))[0] == 0  # the same: a no-op
    rc, _, err = run_cli(capsys, "eval-split", "pin", "--data", str(data))  # all three: another set
    assert rc == 1 and err.count("\n") == 1 and "already pinned" in err and cat.eval_split().ids == evals[:2]
    assert cat.snapshot("train").ids == train  # training never sees them
    episodes.write_episode(tmp_path / "late" / "ep.mcap", make_episode(rng))
    rc, _, err = run_cli(capsys, "ingest", str(tmp_path / "late"), "--split", "eval", "--data", str(data))
    assert rc == 0 and "has its eval split pinned already (fixed for good)" in err and cat.count(split="eval") == 4


def test_eval_split_create_and_show(capsys, data):
    rc, out, err = run_cli(capsys, "eval-split", "show", "--data", str(data))
    assert rc == 2 and "no catalog" in err
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", "--size", "16", "--steps", "3",
                        "--data", str(data), "--json")
    assert rc == 0, err
    digest = json.loads(out)["hash"]
    rc, out, _ = run_cli(capsys, "eval-split", "show", "--data", str(data), "--json")
    shown = json.loads(out)
    assert rc == 0 and shown["hash"] == digest and len(shown["episodes"]) == 4
    rc, out, _ = run_cli(capsys, "eval-split", "show", "--data", str(data))
    assert "T: 1" in out and "disk: 1" in out
    # the same parameters again: same split, nothing collected; other parameters: refused before collecting
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", "--size", "16", "--steps", "3",
                           "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["hash"] == digest and "collecting" not in err
    files = sorted(data.rglob("*.mcap"))
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "6", "--size", "16", "--steps", "5",
                           "--data", str(data))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert (f"{data}'s evaluation split was made with --episodes 4 --steps 3 (asked for --episodes 6 --steps 5): "
            "give those, or another --data") in err
    assert Catalog(data).snapshot().ids == [] and sorted(data.rglob("*.mcap")) == files


@pytest.mark.parametrize("argv,needle", [
    (["collect", "--shape", "star", "--data", "DATA"], "invalid choice: 'star'"),
    (["collect", "--episodes", "0", "--data", "DATA"], "expected a positive integer"),
    (["collect", "--size", "4", "--data", "DATA"], "expected a multiple of 8 from 16"),
    (["collect", "--steps", "5000", "--data", "DATA"], "expected at most 1000 steps"),
    (["collect", "--policy", "teleport", "--data", "DATA"], "invalid choice: 'teleport'"),
    (["collect", "--frobnicate", "--data", "DATA"], "unrecognized arguments: --frobnicate"),
    (["episodes", "ls", "--split", "test", "--data", "DATA"], "invalid choice: 'test'"),
    (["episodes"], "required"),
    (["ingest", "--data", "DATA"], "required"),
    (["eval-split", "create", "--episodes", "x", "--data", "DATA"], "expected a positive integer, found 'x'"),
    (["bench", "sim", "--seconds", "-1"], "expected a positive number"),
])
def test_usage_errors_exit_2_in_one_line(capsys, data, argv, needle):
    rc, out, err = run_cli(capsys, *[str(data) if a == "DATA" else a for a in argv])
    assert rc == 2
    assert needle in err and err.count("\n") == 1, err
    assert not data.exists()  # nothing was created


def test_unknown_paths_and_ids_exit_2(capsys, data, rng, tmp_path):
    rc, _, err = run_cli(capsys, "ingest", str(tmp_path / "nowhere.mcap"), "--data", str(data))
    assert rc == 2 and "no such file or directory" in err and err.count("\n") == 1
    rc, _, err = run_cli(capsys, "episodes", "ls", "--data", str(tmp_path / "nodata"))
    assert rc == 2 and "no catalog at" in err
    Catalog(data).add_episode(make_episode(rng))
    rc, _, err = run_cli(capsys, "episodes", "show", "feedbeef", "--data", str(data))
    assert rc == 2 and "no episode 'feedbeef'" in err and err.count("\n") == 1
    rc, _, err = run_cli(capsys, "episodes", "verify", "feedbeef", "--data", str(data))
    assert rc == 2


def test_console_script_usage_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "orchestrator", "collect", "--shape", "hexagon",
                           "--data", str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "invalid choice: 'hexagon'" in proc.stderr


def test_verify_reports_files_a_crashed_ingest_left_and_serve_moves_them_aside(capsys, data, rng, tmp_path):
    cat = Catalog(data)
    kept = cat.add_episode(make_episode(rng))
    orphan = kept.path.parent / "orphan.mcap"  # renamed into place, then a crash before the commit
    orphan.write_bytes(episodes.encode_episode(make_episode(rng)))
    rc, out, _ = run_cli(capsys, "episodes", "verify", "--data", str(data))
    assert rc == 0 and "1 ok, 0 bad" in out and "left by a crashed ingest" in out and str(orphan) in out
    service = Service(ServiceConfig(data_dir=data, listen=(f"tcp/127.0.0.1:{free_port()}",)))
    service.start()
    service.stop()
    assert not orphan.exists() and (data / "orphans" / orphan.parent.name / orphan.name).is_file()
    rc, out, _ = run_cli(capsys, "episodes", "verify", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["strays"] == []


@pytest.mark.parametrize("argv", [("episodes", "ls"), ("models", "ls"), ("models", "prune", "--keep", "1")])
def test_a_damaged_catalog_is_one_line_and_exit_1(capsys, data, argv):
    data.mkdir()
    (data / "catalog.sqlite").write_bytes(b"not a database, but a file that was overwritten " * 100)
    rc, out, err = run_cli(capsys, *argv, "--data", str(data))
    assert rc == 1 and err.count("\n") == 1 and "catalog.sqlite" in err and "Traceback" not in err


def test_ingest_refuses_a_pipe_and_a_device_without_reading_them(capsys, data, tmp_path):
    fifo = tmp_path / "stuck.mcap"
    os.mkfifo(fifo)  # reading it would wait for a writer for ever
    rc, out, err = run_cli(capsys, "ingest", str(fifo), "/dev/zero", "--data", str(data))
    assert rc == 1 and "0 of 2 files indexed" in out
    assert f"{fifo}: is not a regular file (a pipe or a device?)" in err and "/dev/zero: is not a regular" in err


def test_ingest_of_a_directory_without_episodes_is_a_usage_error(capsys, data, tmp_path):
    (tmp_path / "empty").mkdir()
    rc, _, err = run_cli(capsys, "ingest", str(tmp_path / "empty"), "--data", str(data))
    assert rc == 2 and f"no .mcap files under {tmp_path / 'empty'}" in err
    assert not (data / "catalog.sqlite").exists()


def _damage_table(db, table: str) -> None:
    """Overwrites the root page of ``table`` (small tables live on it whole): SQLite opens the file, and
    reading that table fails with 'database disk image is malformed'."""
    import sqlite3
    with sqlite3.connect(db) as conn:
        page = conn.execute("PRAGMA page_size").fetchone()[0]
        root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = ?", (table,)).fetchone()[0]
    conn.close()
    with open(db, "r+b") as f:
        f.seek((root - 1) * page)
        f.write(b"\xa5" * page)


@pytest.mark.parametrize("argv,table", [
    (("episodes", "show", "EP"), "episodes"), (("episodes", "quarantine", "EP", "--reason", "x"), "episodes"),
    (("models", "show", "V"), "models"), (("eval", "V"), "models"), (("score", "EP"), "episodes"),
])
def test_a_damaged_table_is_exit_1_not_a_usage_error(capsys, data, rng, argv, table):
    from storage.models import ModelRegistry
    ep = make_episode(rng)
    Catalog(data).add_episode(ep)
    version = ModelRegistry(data).register(b"w" * 64, {}, {"h1_mse": 0.1}, "snap", "split")
    argv = [ep.meta.episode_id if a == "EP" else version if a == "V" else a for a in argv]
    _damage_table(data / "catalog.sqlite", table)
    rc, _, err = run_cli(capsys, *argv, "--data", str(data))
    assert rc == 1 and "malformed" in err and err.count("\n") == 1, err


def test_a_path_with_a_newline_is_reported_on_one_line(capsys, data, rng, tmp_path):
    odd = tmp_path / "two\nlines.mcap"
    odd.write_bytes(b"not an episode")
    rc, out, err = run_cli(capsys, "ingest", str(odd), "--data", str(data))
    assert rc == 1 and err.count("\n") == 1 and "two\\nlines.mcap" in err, err
    rc, _, err = run_cli(capsys, "ingest", str(tmp_path / "no\nsuch.mcap"), "--data", str(data))
    assert rc == 2 and err.count("\n") == 1 and "no\\nsuch.mcap" in err, err


def test_ingest_goes_on_past_an_indexed_file_it_cannot_repair(capsys, data, rng, tmp_path):
    cat = Catalog(data)
    first, second = make_episode(rng), make_episode(rng)
    row = cat.get(cat.add_episode(first).episode_id)
    (tmp_path / "a.mcap").write_bytes(row.path.read_bytes())
    episodes.write_episode(tmp_path / "b.mcap", second)
    row.path.unlink()
    row.path.mkdir()  # something in the way of the repair
    rc, out, err = run_cli(capsys, "ingest", str(tmp_path / "a.mcap"), str(tmp_path / "b.mcap"), "--data", str(data))
    assert rc == 1 and "1 of 2 files indexed" in out and f"ingested {second.meta.episode_id}" in out
    assert f"cannot restore episode {first.meta.episode_id}" in err and err.count("\n") == 1, err


def test_collect_with_the_eval_splits_seed_is_refused_in_one_line_and_changes_nothing(capsys, data):
    """The eval split is a function of its seed: `collect --seed 1234` (eval-split create's default) would
    record its episodes again, under new ids, as train episodes."""
    tiny = ("--size", "16", "--steps", "3", "--data", str(data))
    assert run_cli(capsys, "eval-split", "create", "--episodes", "2", *tiny)[0] == 0
    evals = Catalog(data).eval_split().ids
    files = sorted(data.rglob("*.mcap"))
    for extra in ((), ("--steps", "5")):  # longer episodes start as the eval ones do
        rc, out, err = run_cli(capsys, "collect", "--episodes", "3", "--seed", "1234", *tiny, *extra)
        assert rc == 2 and out == "" and err.count("\n") == 1, err
        assert "activecollect: error: --seed 1234 would record eval episode " in err
        assert "replay eval episodes" in err and "would leak the eval split; give another --seed" in err
        assert err.split("eval episode ")[1].split()[0] in evals
        assert sorted(data.rglob("*.mcap")) == files and Catalog(data).count(split="train") == 0
    rc, out, err = run_cli(capsys, "collect", "--episodes", "3", "--seed", "1235", *tiny, "--json")
    assert rc == 0, err
    rc, out, err = run_cli(capsys, "collect", "--episodes", "1", "--seed", "1234", "--policy", "random_waypoints",
                           *tiny)
    assert rc == 0, err  # another policy records other episodes
    assert Catalog(data).count(split="train") == 4


def test_collect_again_with_the_same_seed_is_refused_in_one_line_and_changes_nothing(capsys, data):
    """`collect` twice with the default --seed 0 recorded the same episodes twice, under new ids, without a word
    (an operator's review: "collect 10 more" gave the same 10 again, counted twice in training)."""
    tiny = ("--size", "16", "--steps", "3", "--data", str(data))
    assert run_cli(capsys, "collect", "--episodes", "2", *tiny)[0] == 0
    files, first = sorted(data.rglob("*.mcap")), {row.episode_id for row in Catalog(data).list()}
    for extra in ((), ("--episodes", "3"), ("--steps", "5")):  # (more of them, or longer: they start the same)
        rc, out, err = run_cli(capsys, "collect", "--episodes", "2", *tiny, *extra)
        assert rc == 2 and out == "" and err.count("\n") == 1, err
        assert err.startswith("activecollect: error: --seed 0 would record train episode ")
        assert err.rstrip().endswith("give another --seed")
        assert err.split("train episode ")[1].split()[0] in first
        assert sorted(data.rglob("*.mcap")) == files
    assert run_cli(capsys, "collect", "--episodes", "2", "--seed", "1", *tiny)[0] == 0
    assert Catalog(data).count(split="train") == 4


def test_eval_split_create_over_train_copies_of_its_episodes_is_refused_before_collecting(capsys, data):
    tiny = ("--size", "16", "--steps", "3", "--data", str(data))
    assert run_cli(capsys, "collect", "--episodes", "2", "--seed", "1234", *tiny)[0] == 0
    train = Catalog(data).snapshot().ids
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", *tiny)
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "--seed 1234 would record train episode " in err and "again as an eval episode (2 of the 4" in err
    assert err.split("train episode ")[1].split()[0] in train
    assert Catalog(data).count() == 2 and Catalog(data).eval_split() is None
    # run, which makes the split itself, refuses the same (exit 2, naming its own flag) before it starts anything
    rc, out, err = run_cli(capsys, "run", "--data", str(data), "--image-size", "16", "--steps", "3",
                           "--eval-episodes", "4", "--budget", "4", "--no-progress")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "--eval-seed 1234 would record train episode " in err and err.rstrip().endswith("give another --eval-seed")
    assert Catalog(data).count() == 2 and Catalog(data).eval_split() is None
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", "--seed", "99", *tiny)
    assert rc == 0, err


def test_ingesting_another_directorys_eval_episodes_as_train_is_refused_per_file(capsys, data, tmp_path):
    """Two data directories whose eval splits were made alike hold the same eval episodes under other ids."""
    other = tmp_path / "other"
    tiny = ("--size", "16", "--steps", "3")
    assert run_cli(capsys, "eval-split", "create", "--episodes", "2", *tiny, "--data", str(other))[0] == 0
    assert run_cli(capsys, "collect", "--episodes", "1", "--seed", "7", *tiny, "--data", str(other))[0] == 0
    assert run_cli(capsys, "eval-split", "create", "--episodes", "2", *tiny, "--data", str(data))[0] == 0
    theirs = Catalog(other).eval_split().ids
    ours = Catalog(data).eval_split().ids
    files = sorted(data.rglob("*.mcap"))
    rc, out, err = run_cli(capsys, "ingest", str(other / "episodes"), "--data", str(data), "--json")
    report = json.loads(out)
    assert rc == 1 and report["ingested"] == 1 and report["refused"] == 2  # their train episode goes in
    for entry in report["files"]:
        refused_id = entry["path"].rsplit("/", 1)[1].removesuffix(".mcap")
        assert entry["ok"] is (refused_id not in theirs)
        if not entry["ok"]:
            assert entry["error"].startswith(f"CatalogError: episode {refused_id} replays eval episode ")
            assert entry["error"].split("eval episode ")[1].split()[0] in ours
            assert "training on it would leak the eval split" in entry["error"]
    assert err.count("\n") == 2 and err.count("refused") == 2 and "replays eval episode" in err
    cat = Catalog(data)
    assert len(sorted(data.rglob("*.mcap"))) == len(files) + 1 and cat.count(split="train") == 1
    assert cat.eval_split().ids == ours


def test_eval_split_show_after_an_interrupted_create_says_to_run_create_again(capsys, tmp_path, monkeypatch):
    """A create stopped midway leaves unpinned eval episodes. `eval-split show` used to tell the operator only to
    pin them with `eval-split pin`, which pins the partial split for good (a pinned split is never replaced);
    it now says that running the create again finishes it, and doing so pins the whole split."""
    import workers.collect as wc

    data = tmp_path / "d"
    real, calls = wc.collect_episode, [0]

    def interrupted(*a, **kw):
        calls[0] += 1
        if calls[0] == 4:  # (the operator's Ctrl-C, in the middle of the fourth episode)
            raise KeyboardInterrupt
        return real(*a, **kw)

    monkeypatch.setattr(wc, "collect_episode", interrupted)
    args = ("eval-split", "create", "--data", str(data), "--episodes", "8", "--steps", "5", "--size", "16")
    rc, _, _ = run_cli(capsys, *args)
    assert rc == 130 and Catalog(data).eval_split() is None and Catalog(data).count(split="eval") == 3
    rc, _, err = run_cli(capsys, "eval-split", "show", "--data", str(data))
    assert rc == 1 and len(err.strip().splitlines()) == 1, err
    assert "3 eval episodes are indexed, not pinned" in err and "run again with the same flags" in err, err
    monkeypatch.setattr(wc, "collect_episode", real)
    rc, _, err = run_cli(capsys, *args)
    assert rc == 0, err
    assert len(Catalog(data).eval_split().ids) == 8 and Catalog(data).count(split="eval") == 8
