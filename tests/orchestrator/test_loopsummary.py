"""``bench loop-summary DIR``: a run's summary rebuilt from the configuration and points it left, the same as the
one the run writes itself; a directory it cannot summarise is refused with the reason and left as it was."""

from __future__ import annotations

import json

import pytest

from orchestrator.cli.collect import make_eval_split
from orchestrator.cli.loopbench import bench_collect
from orchestrator.loopbench import LoopBenchConfig, run_bench
from orchestrator.loopsummary import ARM_POINTS, CONFIG, SUMMARY, SummaryError, arm_dir, rebuild, write_config
from tests.conftest import run_cli
from uncertainty.config import TrainConfig


def test_a_finished_runs_rebuilt_summary_is_the_one_it_wrote(tmp_path):
    cfg = LoopBenchConfig(seeds=(0,), budget=4, round_episodes=2, steps=12, image_size=16,
                          train=TrainConfig(members=2, epochs=1, batch_size=8, widths=(4, 8, 8), device="cpu",
                                            progress=False, min_rel_improvement=0.0))
    own = run_bench(cfg, tmp_path, bench_collect, make_eval_split, log=lambda line: None, threads=1)
    written = (tmp_path / SUMMARY).read_bytes()
    with pytest.raises(SummaryError, match="was written by the run itself; it is kept"):
        rebuild(tmp_path)
    assert (tmp_path / SUMMARY).read_bytes() == written
    (tmp_path / SUMMARY).unlink()
    again = json.loads(json.dumps(rebuild(tmp_path)))
    own = json.loads(json.dumps(own))
    assert {k: again[k] for k in ("config", "points", "h1", "h5", "jobs", "threads", "transport")} == {
        k: own[k] for k in ("config", "points", "h1", "h5", "jobs", "threads", "transport")}
    assert (again["rebuilt"], again["interrupted"], again["stopped_by"], again["seconds"]) == (True, False, None, None)
    assert json.loads((tmp_path / SUMMARY).read_text()) == again


def _stopped_run(out, points: dict[tuple[int, str], list[int]]) -> None:
    """An output directory as a killed run leaves it: its configuration and each arm's points (episodes given)."""
    write_config(out, LoopBenchConfig(seeds=(0, 1), budget=8, round_episodes=2).to_json(), 1, None)
    for (seed, arm), episodes in points.items():
        arm_dir(out, seed, arm).mkdir(parents=True)
        (arm_dir(out, seed, arm) / ARM_POINTS).write_text(json.dumps(
            [{"arm": arm, "seed": seed, "episodes": e, "h1_mse": 1 / e, "h5_mse": 2 / e} for e in episodes]))


def test_the_rounds_both_arms_of_a_seed_finished_are_compared(tmp_path, capsys):
    _stopped_run(tmp_path, {(0, "active"): [2, 4, 6], (0, "uniform"): [2, 4], (1, "active"): [2]})
    rc, stdout, err = run_cli(capsys, "bench", "loop-summary", "--json", str(tmp_path))
    assert rc == 0, err
    summary = json.loads(stdout)
    assert len(summary["points"]) == 6 and summary["interrupted"] and summary["h1"]["headline"]["budget"] == 4
    assert [r["seed"] for r in summary["h1"]["per_seed"]] == [0] and (tmp_path / "loop.png").is_file()


@pytest.mark.parametrize("damage, code, message", [
    (lambda d: (d / CONFIG).unlink(), 2, "holds no config.json: not the --out of a bench loop run"),
    (lambda d: (d / CONFIG).write_text('{"config": {"seeds": [0'), 1, "config.json: not JSON"),
    (lambda d: (d / CONFIG).write_text('{"config": {"budget": 8}}'), 1,
     "config.json: not a bench loop configuration (KeyError: 'seeds')"),
    (lambda d: (arm_dir(d, 0, "uniform") / ARM_POINTS).write_text("[{"), 1, "uniform/points.json: not JSON"),
    (lambda d: (arm_dir(d, 0, "uniform") / ARM_POINTS).write_text('[{"arm": "active", "seed": 0, "episodes": 2}]'),
     1, "uniform/points.json: not the points of the uniform arm of seed 0"),
    (lambda d: (arm_dir(d, 0, "active") / ARM_POINTS).write_text(
        '[{"arm": "active", "seed": 0, "episodes": 2, "h1_mse": null, "h5_mse": 1.0}]'),
     1, "active/points.json: not the points of the active arm of seed 0"),
    (lambda d: [(arm_dir(d, 0, arm) / ARM_POINTS).unlink() for arm in ("active", "uniform")], 1,
     "no round had finished in"),
    (lambda d: ((arm_dir(d, 0, "uniform") / ARM_POINTS).unlink(), (arm_dir(d, 0, "uniform") / ARM_POINTS).mkdir()),
     1, "uniform/points.json: cannot read it (Is a directory)"),
])
def test_a_directory_it_cannot_summarise_is_refused_with_the_reason(tmp_path, capsys, damage, code, message):
    _stopped_run(tmp_path, {(0, "active"): [2, 4], (0, "uniform"): [2, 4]})
    damage(tmp_path)
    rc, stdout, err = run_cli(capsys, "bench", "loop-summary", str(tmp_path))
    assert rc == code and message in err and stdout == "", err
    assert not (tmp_path / SUMMARY).exists() and not (tmp_path / "loop.png").exists()


def test_a_damaged_summary_is_rebuilt_and_a_missing_directory_refused(tmp_path, capsys):
    _stopped_run(tmp_path, {(0, "active"): [2, 4], (0, "uniform"): [2, 4], (1, "active"): [2], (1, "uniform"): [2]})
    (tmp_path / SUMMARY).write_text('{"points": [')
    rc, stdout, err = run_cli(capsys, "bench", "loop-summary", str(tmp_path))
    assert rc == 0 and json.loads((tmp_path / SUMMARY).read_text())["rebuilt"] is True, err
    assert "active's final over uniform's, per seed" in stdout
    rc, _, err = run_cli(capsys, "bench", "loop-summary", str(tmp_path / "nowhere"))
    assert rc == 2 and "no such directory" in err


def test_a_stopped_runs_plot_draws_the_points_its_headline_compares():
    """Seed 1's uniform arm stopped a round short: its active point at 4 was drawn, so the active arm's mean at 4
    was of two seeds and the uniform arm's of one."""
    from orchestrator.loopsummary import figure
    points = [{"arm": arm, "seed": seed, "episodes": n, "h1_mse": 0.01 * (seed + 1), "h5_mse": 0.02}
              for seed in (0, 1) for arm in ("active", "uniform") for n in (2, 4)
              if (seed, arm, n) != (1, "uniform", 4)]
    ax = figure(points).axes[0]
    assert {label: list(line.get_xdata()) for line, label in zip(*ax.get_legend_handles_labels())} == {
        "active (mean of 1 to 2 seeds per point)": [2, 4], "uniform (mean of 1 to 2 seeds per point)": [2, 4]}
    assert [round(y, 4) for y in ax.get_lines()[0].get_ydata()] == [0.015, 0.01]  # at 4: seed 0 alone
    one_arm = [p for p in points if p["arm"] == "active"]  # stopped before any uniform arm finished a round
    assert [t.get_text() for ax in figure(one_arm).axes for t in ax.texts] == [
        "no episode count that both arms reached yet"] * 2


@pytest.mark.parametrize("name", ["loop.png", SUMMARY])
def test_a_directory_where_an_output_goes_is_named_in_one_line_and_nothing_written(tmp_path, capsys, name):
    """It was a raw "[Errno 21] Is a directory" line (and loop.png was written before summary.json failed)."""
    _stopped_run(tmp_path, {(0, "active"): [2, 4], (0, "uniform"): [2, 4]})
    (tmp_path / name).mkdir()
    rc, stdout, err = run_cli(capsys, "bench", "loop-summary", str(tmp_path))
    assert rc == 1 and stdout == "" and err.count("\n") == 1, err
    assert err == (f"activecollect: cannot summarise: cannot write {tmp_path / name}: a directory is in its place "
                   "(move it away)\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([CONFIG, "seed0", name])
    assert list((tmp_path / name).iterdir()) == []
