"""The data commands (collect, ingest, episodes, eval-split) under an operator's hostile input: empty paths,
numbers past what SQLite or memory hold, an id given twice, Ctrl-C in the middle of many episodes."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orchestrator.cli import build_parser
from storage import episodes
from storage.catalog import Catalog
from storage.database import DB_NAME
from tests.conftest import REPO, run_cli, wait_for
from tests.storage.test_episodes import make_episode


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(17)


def _one_line(err: str) -> bool:
    return err.count("\n") == 1 and "Traceback" not in err


def test_ls_limit_past_what_sqlite_holds_lists_them_all(capsys, data_dir, rng):
    ids = [Catalog(data_dir).add_episode(make_episode(rng)).episode_id for _ in range(2)]
    rc, out, err = run_cli(capsys, "episodes", "ls", "--limit", str(10**20), "--data", str(data_dir))
    assert rc == 0, err
    assert all(i in out for i in ids) and "2 of 2 episodes" in out


@pytest.mark.parametrize("argv", [
    ["collect", "--episodes", "1", "--size", "16", "--steps", "4", "--data", ""],
    ["eval-split", "create", "--episodes", "1", "--size", "16", "--steps", "4", "--data", ""],
    ["ingest", "", "--data", "DATA"],
    ["ingest", "--data", "", "FILE"],
])
def test_an_empty_path_is_a_usage_error_not_this_directory(capsys, monkeypatch, tmp_path, rng, argv):
    """An unset shell variable ($DATA, $DIR) is not the current directory: nothing is made or read there."""
    here = tmp_path / "here"
    here.mkdir()
    episodes.write_episode(here / "loose.mcap", make_episode(rng))
    monkeypatch.chdir(here)
    data = tmp_path / "data"
    argv = [str(data) if a == "DATA" else str(here / "loose.mcap") if a == "FILE" else a for a in argv]
    rc, _, err = run_cli(capsys, *argv)
    assert rc == 2 and "empty path" in err and _one_line(err), err
    assert sorted(p.name for p in here.iterdir()) == ["loose.mcap"] and not data.exists()


@pytest.mark.parametrize("command", [["collect"], ["eval-split", "create"]])
@pytest.mark.parametrize("episodes_asked", [str(10**20), "100001"])
def test_episodes_past_the_cap_are_refused_before_any_planning(capsys, tmp_path, command, episodes_asked):
    # (parsed only: before, `collect --episodes 10**20` planned episodes in memory until the machine ran out)
    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args([*command, "--episodes", episodes_asked, "--data", str(tmp_path / "d")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "at most 100000 episodes" in err and _one_line(err), err


def test_an_id_given_twice_is_one_episode(capsys, data_dir, rng):
    cat = Catalog(data_dir)
    ids = [cat.add_episode(make_episode(rng)).episode_id for _ in range(2)]
    rc, out, err = run_cli(capsys, "episodes", "quarantine", ids[0], ids[0][:8], "--reason", "smudged",
                           "--data", str(data_dir))
    assert rc == 0 and out == f"quarantined {ids[0]}: smudged\n", (out, err)
    rc, out, err = run_cli(capsys, "episodes", "restore", ids[0][:8], ids[0], "--data", str(data_dir), "--json")
    assert rc == 0 and err == "", err  # (was: restored, then "is not quarantined", exit 1)
    assert [r["episode_id"] for r in json.loads(out)] == [ids[0]]
    rc, out, _ = run_cli(capsys, "episodes", "verify", ids[1], ids[1], "--data", str(data_dir))
    assert rc == 0 and "verified 1 episodes: 1 ok" in out
    assert sorted(cat.snapshot().ids) == sorted(ids)


def _cli(*argv: str, **kwargs) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "orchestrator", *argv], cwd=REPO, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kwargs)


def _indexed(data) -> int:
    return Catalog(data).count() if (data / DB_NAME).is_file() else 0


def _published(data) -> int:
    """Episode files in place, counted without opening the catalog: a reader opening it while the command
    makes it can fail the command's first connection ("database is locked")."""
    return len(list((data / "episodes").glob("*/*.mcap")))


def test_ctrl_c_in_collect_says_what_is_kept_and_why_the_same_seed_is_refused(capsys, tmp_path):
    data = tmp_path / "data"
    proc = _cli("collect", "--episodes", "1000", "--size", "16", "--steps", "30", "--data", str(data))
    try:
        wait_for(lambda: _published(data) >= 3 or proc.poll() is not None, timeout=60, message="3 episodes")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    kept = _indexed(data)
    assert proc.returncode == 130 and out == "", (out, err)
    assert err == (f"activecollect: interrupted: {kept} of the 1000 episodes asked for are indexed in {data} and "
                   "kept; --seed 0 would record them again: give another --seed for more\n")
    assert 2 <= kept < 1000
    for row in Catalog(data).list():
        Catalog(data).verify(row.episode_id)  # each one said to be kept is whole
    rc, _, err = run_cli(capsys, "collect", "--episodes", "1000", "--size", "16", "--steps", "30", "--data", str(data))
    assert rc == 2 and "give another --seed" in err and Catalog(data).count() == kept


def _ingest_interrupted(tmp_path, rng, n: int, *flags: str) -> tuple[Path, Path, subprocess.Popen, str, str]:
    """``ingest`` of ``n`` small files into a new ``data``, Ctrl-C once 3 are indexed: (files, data, the process,
    its stdout, its stderr)."""
    files = tmp_path / "files"
    files.mkdir()
    for i in range(n):
        episodes.write_episode(files / f"e{i:03}.mcap", make_episode(rng, steps=3))
    data = tmp_path / "data"
    proc = _cli("ingest", str(files), "--data", str(data), *flags)
    try:
        wait_for(lambda: _published(data) >= 3 or proc.poll() is not None, timeout=60, message="3 files indexed")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    return files, data, proc, out, err


def test_ctrl_c_in_ingest_says_what_is_kept_and_a_second_run_indexes_the_rest(tmp_path, rng):
    files, data, proc, out, err = _ingest_interrupted(tmp_path, rng, 600)
    kept = _indexed(data)
    assert proc.returncode == 130, (out[-300:], err)
    said = re.fullmatch(r"activecollect: interrupted at file (\d+) of 600 \((.*)\): the (\d+) indexed before it are "
                        r"kept; run it again to index the rest \(files already indexed are not indexed twice\)",
                        err.splitlines()[-1])
    assert said, err
    before = int(said[3])  # (the file in hand may have been indexed as the signal came)
    assert int(said[1]) == before + 1 and said[2] == str(files / f"e{before:03}.mcap") and kept - 1 <= before <= kept
    again = _cli("ingest", str(files), "--data", str(data))
    out, err = again.communicate(timeout=120)
    assert again.returncode == 0 and out.endswith(f"600 of 600 files indexed in {data / DB_NAME}\n"), err
    assert Catalog(data).count() == 600 and out.count("already indexed") == kept


def test_ctrl_c_in_ingest_json_prints_what_was_indexed_so_far_marked_interrupted(tmp_path, rng):
    """``ingest --json`` interrupted printed nothing on stdout: a script reading it got no JSON at all."""
    files, data, proc, out, err = _ingest_interrupted(tmp_path, rng, 300, "--json")
    assert proc.returncode == 130 and "activecollect: interrupted at file" in err, (out[-300:], err)
    result = json.loads(out)
    indexed = int(re.search(r"the (\d+) indexed before it are kept", err)[1])
    assert result["interrupted"] is True and result["refused"] == 0 and result["ingested"] == indexed >= 2
    assert [f["path"] for f in result["files"]] == [str(files / f"e{i:03}.mcap") for i in range(indexed)]
    assert {f["episode_id"] for f in result["files"]} <= {r.episode_id for r in Catalog(data).list()}


@pytest.mark.parametrize("argv", [("collect", "--episodes", "1", "--steps", "3"), ("ingest", "EP")])
def test_a_file_where_the_episodes_folder_goes_is_named_in_one_line(capsys, tmp_path, argv) -> None:
    """collect and ingest into a directory whose ``episodes`` is a file said only "[Errno 17] File exists"; nothing
    is made beside it."""
    data = tmp_path / "data"
    data.mkdir()
    (data / "episodes").write_text("not a folder")
    episode = tmp_path / "ep.mcap"
    episode.write_bytes(episodes.encode_episode(make_episode(np.random.default_rng(0), steps=3)))
    rc, out, err = run_cli(capsys, *(str(episode) if a == "EP" else a for a in argv), "--data", str(data))
    assert rc == 1 and err.count("\n") == 1, err  # (ingest: the file refused for it, and its count on stdout)
    assert f"{data / 'episodes'} is not a directory: the catalog keeps its episode files there; move the file away" \
        in err
    assert sorted(p.name for p in data.iterdir()) == ["episodes"]


@pytest.mark.parametrize("argv", [("episodes", "ls"), ("ingest", "EP")])
def test_a_dangling_link_where_the_episodes_folder_goes_is_named_as_a_link(capsys, tmp_path, argv) -> None:
    """``DATA/episodes`` a link to a volume not mounted: it said "not a directory ... move the file away", advice that
    would start an empty episodes/ beside the catalog that indexes the volume's files."""
    data = tmp_path / "data"
    Catalog(data)
    (data / "episodes").rmdir()
    (data / "episodes").symlink_to(tmp_path / "volume" / "episodes")
    episode = tmp_path / "ep.mcap"
    episode.write_bytes(episodes.encode_episode(make_episode(np.random.default_rng(0), steps=3)))
    rc, _, err = run_cli(capsys, *(str(episode) if a == "EP" else a for a in argv), "--data", str(data))
    assert rc == 1 and err.count("\n") == 1, err
    assert (f"{data / 'episodes'} is a link to {tmp_path / 'volume' / 'episodes'}, which is not a directory (a volume "
            "not mounted?): the catalog keeps its episode files there; mount it, or point the link at the folder") \
        in err
    assert "move the file away" not in err
    assert (data / "episodes").is_symlink() and not (tmp_path / "volume").exists()
