"""The catalog commands that only read (``episodes ls|show|verify``, ``eval-split show``, ``eval``, ``score ID``) make
no ``episodes/`` folder in a data directory that has none (its folder gone: a volume not mounted, an operator's rm);
the commands that write (``episodes quarantine``, ``ingest``, ...) still make it."""

from __future__ import annotations

import shutil

import pytest

from orchestrator.cli import main
from storage.catalog import Catalog
from tests.conftest import run_cli
from tests.test_cli_models import small_catalog


def _entries(data) -> set[str]:
    """The data directory's entries, all the way down, but the database's own -wal/-shm (SQLite's, on any read)."""
    return {str(p.relative_to(data)) for p in data.rglob("*") if not p.name.startswith("catalog.sqlite-")}


@pytest.fixture
def data(tmp_path):
    """A catalog of two train and one pinned eval episode, its episodes/ folder gone."""
    data = small_catalog(tmp_path / "data", seed=3, train=2, eval_=1)
    shutil.rmtree(data / "episodes")
    return data


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A data dir with a champion trained on 4 train episodes, evaluated on 2 pinned ones."""
    data = small_catalog(tmp_path_factory.mktemp("trained") / "data", seed=7, train=4, eval_=2)
    assert main(["train", "--data", str(data), "--members", "2", "--epochs", "1", "--device", "cpu"]) == 0
    return data


# (argv, exit status, what stdout or stderr says); ID: a train episode's id prefix
READS = [
    (("episodes", "ls"), 0, "3 of 3 episodes"),
    (("episodes", "ls", "--quarantined", "--json"), 0, "[]"),
    (("episodes", "show", "ID"), 0, "episode_id"),
    (("episodes", "verify"), 1, "verified 3 episodes: 0 ok, 3 bad"),
    (("eval-split", "show"), 0, "episodes  1 (box: 1)"),
    (("eval",), 1, "no champion model yet"),
    (("score", "ID"), 1, "is missing: re-ingest its bytes"),
]


@pytest.mark.parametrize("argv,rc,says", READS, ids=[" ".join(argv) for argv, _, _ in READS])
def test_a_reading_command_makes_no_episodes_folder(capsys, data, argv, rc, says) -> None:
    prefix = Catalog(data, make_episodes_dir=False).list(split="train")[0].episode_id[:10]
    before = _entries(data)
    assert "episodes" not in before
    got, out, err = run_cli(capsys, *(prefix if a == "ID" else a for a in argv), "--data", str(data))
    assert got == rc and says in out + err, (out, err)
    assert _entries(data) == before


@pytest.mark.parametrize("argv", [("eval",), ("score", "ID")], ids=" ".join)
def test_eval_and_score_with_a_champion_make_no_episodes_folder(capsys, tmp_path, trained, argv) -> None:
    data = tmp_path / "data"
    shutil.copytree(trained, data)
    shutil.rmtree(data / "episodes")
    prefix = Catalog(data, make_episodes_dir=False).list(split="train")[0].episode_id[:10]
    before = _entries(data)
    got, out, err = run_cli(capsys, *(prefix if a == "ID" else a for a in argv), "--data", str(data),
                            "--device", "cpu")
    assert got == 1 and len(err.strip().splitlines()) == 1, (out, err)  # the episodes' files are gone
    assert _entries(data) == before


def test_a_writing_command_still_makes_the_episodes_folder(capsys, data) -> None:
    row = Catalog(data, make_episodes_dir=False).list(split="train")[0]
    rc, out, err = run_cli(capsys, "episodes", "quarantine", row.episode_id, "--reason", "test", "--data", str(data))
    assert rc == 0 and (data / "episodes").is_dir(), (out, err)


@pytest.mark.parametrize("argv", [("episodes", "ls"), ("episodes", "verify"), ("eval-split", "show"),
                                  ("score", "ID")], ids=" ".join)
def test_a_reading_command_names_a_file_where_episodes_go(capsys, data, argv) -> None:
    (data / "episodes").write_bytes(b"not a folder")
    got, out, err = run_cli(capsys, *("0123456789" if a == "ID" else a for a in argv), "--data", str(data))
    assert got != 0 and len(err.strip().splitlines()) == 1 and "episodes is not a directory" in err, (out, err)


# (argv, what stderr says): a command that would write, refused (exit 2) before it writes anything
REFUSED = [
    (("collect", "--episodes", "1", "--size", "32"), "holds 16px episodes"),
    (("eval-split", "create", "--episodes", "2", "--size", "16", "--steps", "12"), "evaluation split was made with"),
]


@pytest.mark.parametrize("argv,says", REFUSED, ids=[" ".join(argv) for argv, _ in REFUSED])
def test_a_refused_writing_command_makes_no_episodes_folder(capsys, data, argv, says) -> None:
    before = _entries(data)
    got, out, err = run_cli(capsys, *argv, "--data", str(data))
    assert got == 2 and says in err and len(err.strip().splitlines()) == 1, (out, err)
    assert _entries(data) == before


def test_a_refused_collect_of_the_same_episodes_again_makes_no_episodes_folder(capsys, tmp_path) -> None:
    data, argv = tmp_path / "data", ("collect", "--episodes", "1", "--size", "16", "--seed", "5")
    assert run_cli(capsys, *argv, "--data", str(data))[0] == 0
    shutil.rmtree(data / "episodes")
    before = _entries(data)
    got, out, err = run_cli(capsys, *argv, "--data", str(data))
    assert got == 2 and "would record train episode" in err and len(err.strip().splitlines()) == 1, (out, err)
    assert _entries(data) == before
