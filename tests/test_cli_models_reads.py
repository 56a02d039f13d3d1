"""The model commands that only read (``models ls``, ``models show``, ``eval``, ``score``) make no ``models/`` folder
in a data directory that has none (no model trained yet, or its folder gone): they answer as they would with one."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from storage.catalog import Catalog
from storage.episodes import write_episode
from storage.models import ModelRegistry
from tests.conftest import run_cli
from tests.test_cli_models import _episode

# (argv, exit status, what stdout or stderr says) with no model registered
NEVER_TRAINED = [
    (("models", "ls"), 0, "no models registered in"),
    (("models", "ls", "--json"), 0, '"models": []'),
    (("models", "show", "champion"), 1, "no champion model yet"),
    (("models", "show", "m000001"), 2, "the registry is empty"),
    (("eval",), 1, "no champion model yet"),
    (("score", "EPISODE"), 1, "no champion model yet"),
]


def _entries(data) -> set[str]:
    """The data directory's entries, all the way down, but the database's own -wal/-shm (SQLite's, on any read)."""
    return {str(p.relative_to(data)) for p in data.rglob("*") if not p.name.startswith("catalog.sqlite-")}


def _argv(argv: tuple[str, ...], episode: str) -> list[str]:
    return [episode if a == "EPISODE" else a for a in argv]


@pytest.mark.parametrize("argv,rc,says", NEVER_TRAINED, ids=[" ".join(argv) for argv, _, _ in NEVER_TRAINED])
def test_a_reading_command_makes_no_models_folder(capsys, tmp_path, argv, rc, says) -> None:
    data = tmp_path / "data"
    Catalog(data).episodes_dir.rmdir()  # the catalog alone
    episode = tmp_path / "one.mcap"  # (outside the data directory: score reads it from its path)
    write_episode(episode, _episode(np.random.default_rng(1)))
    before = _entries(data)
    assert before == {"catalog.sqlite"}
    got, out, err = run_cli(capsys, *_argv(argv, str(episode)), "--data", str(data))
    assert got == rc and says in out + err, (out, err)
    assert _entries(data) == before


@pytest.mark.parametrize("argv", [("models", "ls"), ("models", "show", "champion"), ("eval",)],
                         ids=" ".join)
def test_a_reading_command_makes_no_models_folder_where_one_was_removed(capsys, tmp_path, argv) -> None:
    data = tmp_path / "data"
    Catalog(data).episodes_dir.rmdir()
    registry = ModelRegistry(data)
    champion = registry.register(b"weights", {"members": 2}, {"h1_mse": 0.01}, "snap", "split-a")
    registry.gate(champion)
    shutil.rmtree(registry.models_dir)  # rows left, their folder gone (a volume not mounted, an operator's rm)
    before = _entries(data)
    got, out, err = run_cli(capsys, *argv, "--data", str(data))
    assert (got, champion in out + err) == ((1, True) if argv == ("eval",) else (0, True)), (out, err)
    assert _entries(data) == before


def test_promote_and_rollback_read_the_eval_split_without_making_an_episodes_folder(capsys, tmp_path) -> None:
    """They change the registry's rows only: the catalog is read for its pinned split, and makes no episodes/."""
    data = tmp_path / "data"
    Catalog(data).episodes_dir.rmdir()
    registry = ModelRegistry(data)
    first, second = (registry.register(f"w{i}".encode(), {"members": 2}, {"h1_mse": 0.1 / (i + 1)}, "snap", "split-a")
                     for i in range(2))
    registry.gate(first)
    for argv in (("models", "promote", second), ("models", "rollback")):
        got, out, err = run_cli(capsys, *argv, "--data", str(data))
        assert got == 0, (out, err)
        assert "episodes" not in _entries(data)
    assert registry.champion() == first
