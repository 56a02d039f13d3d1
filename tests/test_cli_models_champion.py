"""``champion``, the registry's alias, wherever the model commands take a VERSION: ``models show``, ``models
promote`` (a no-op that says so) and ``eval``; with no champion, one line and exit 1."""

from __future__ import annotations

import json
import re

import pytest

from storage.models import ModelRegistry, ModelStatus
from tests.conftest import run_cli
from tests.test_cli_models import _register, small_catalog


@pytest.fixture
def reg(tmp_path) -> ModelRegistry:
    """The registry of a new data directory (``reg.data_dir``)."""
    return ModelRegistry(tmp_path / "data")


def test_models_show_and_promote_take_champion_for_the_champion(capsys, reg) -> None:
    data = reg.data_dir
    a, b = _register(reg, 0.01), _register(reg, 0.5)
    assert all(re.fullmatch(r"m\d{6}-[0-9a-f]{8}", v) for v in (a, b))  # no version is, or starts, 'champion'
    reg.gate(a)
    reg.gate(b)  # rejected: a stays champion
    rc, out, err = run_cli(capsys, "models", "show", "champion", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["version"] == a and err == "", err
    rc, out, err = run_cli(capsys, "models", "show", "champion", "--data", str(data))
    assert rc == 0 and out.startswith(f"version          {a}\n"), err
    rc, out, err = run_cli(capsys, "models", "promote", "champion", "--data", str(data))
    assert rc == 0 and out == f"{a} is already the champion\n" and err == "", err
    rc, out, _ = run_cli(capsys, "models", "promote", "champion", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["promoted"] is False
    assert reg.champion() == a and [e.version for e in reg.history()] == [a]  # the no-op changed nothing
    reg.promote(b)
    rc, out, _ = run_cli(capsys, "models", "show", "champion", "--data", str(data), "--json")
    assert rc == 0 and json.loads(out)["version"] == b  # the alias follows the champion


@pytest.mark.parametrize("argv", [("models", "show", "champion"), ("models", "promote", "champion"),
                                  ("eval", "champion")])
@pytest.mark.parametrize("models", [0, 1])
def test_champion_with_no_champion_is_one_line_and_exit_1_and_changes_nothing(capsys, reg, argv, models) -> None:
    data = reg.data_dir
    candidates = [_register(reg, 0.01) for _ in range(models)]
    rc, out, err = run_cli(capsys, *argv, "--data", str(data))
    assert rc == 1 and out == "" and err.count("\n") == 1, err
    assert "no champion model yet: 'champion' names none (train one first: activecollect train)" in err
    assert reg.champion() is None and [(m.version, m.status) for m in reg.list()] == [
        (v, ModelStatus.CANDIDATE) for v in candidates]


def test_eval_champion_evaluates_the_champion(capsys, tmp_path) -> None:
    data = small_catalog(tmp_path / "data", seed=3, train=4, eval_=2)
    rc, _, err = run_cli(capsys, "train", "--data", str(data), "--members", "2", "--epochs", "1", "--device", "cpu")
    assert rc == 0, err
    rc, out, err = run_cli(capsys, "eval", "champion", "--data", str(data), "--device", "cpu", "--json")
    assert rc == 0 and json.loads(out)["version"] == ModelRegistry(data).champion(), err
