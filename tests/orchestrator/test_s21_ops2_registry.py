"""A metric with no value (NaN: a Spearman over disagreements that are all equal) reads "undefined" in the
CLI's text, not "nan"; a metric not recorded still reads "-"."""

from __future__ import annotations

from orchestrator.cli.models import _print_eval
from orchestrator.cli.registry import SPEARMAN_UNDEFINED, num
from storage.models import ModelRegistry
from tests.conftest import run_cli

NAN = float("nan")


def test_num_says_undefined_for_nan_and_dash_for_what_is_not_a_number() -> None:
    assert (num(NAN), num(NAN, ".3f", "undefined: why")) == ("undefined", "undefined: why")
    assert (num(None), num("x"), num(True)) == ("-", "-", "-")
    assert (num(0.123456), num(2, ".2f"), num(float("inf"), ".2f")) == ("0.12346", "2.00", "inf")  # PSNR of a 0 MSE


def test_models_show_and_ls_say_undefined_not_nan(capsys, tmp_path) -> None:
    data = tmp_path / "data"
    version = ModelRegistry(data).register(b"weights", {"members": 2},
                                           {"h1_mse": NAN, "h1_psnr": NAN, "spearman": NAN, "spearman_total": 0.25},
                                           "snap", "split")
    rc, out, err = run_cli(capsys, "models", "show", version, "--data", str(data))
    assert rc == 0 and "nan" not in out, out
    lines = {line.split()[0]: line.split(None, 1)[1] for line in out.splitlines() if line.startswith("  ")}
    assert lines["spearman"] == SPEARMAN_UNDEFINED and lines["h1_mse"] == "undefined", lines
    assert lines["spearman_total"] == "0.25", lines
    rc, out, err = run_cli(capsys, "models", "ls", "--data", str(data))
    row = next(line for line in out.splitlines() if version in line)
    assert rc == 0 and row.split()[2:4] == ["undefined", "undefined"], out


def test_eval_text_says_the_spearman_is_undefined(capsys) -> None:
    """``activecollect eval``'s text for an ensemble whose members disagree equally on every window."""
    _print_eval({"h1_mse": 0.01, "h1_psnr": 20.0, "h1_ssim": 0.9, "baseline_h1_mse": 0.02, "baseline_h1_psnr": 17.0,
                 "spearman": NAN, "eval_episodes": 2, "eval_windows": 40})
    out = capsys.readouterr().out
    assert "spearman(disagreement, error) undefined" in out and "nan" not in out, out
