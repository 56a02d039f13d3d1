"""The figure scripts under bench/ still run end to end (tiny sizes; the figures themselves are in BENCHMARKS.md)."""

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from storage.catalog import Catalog
from storage.models import ModelRegistry

ROOT = Path(__file__).resolve().parents[1]


def test_uncertainty_figures_run_in_the_per_shape_palette_world(tmp_path):
    data, out = tmp_path / "data", tmp_path / "figures.json"
    argv = [sys.executable, str(ROOT / "bench" / "uncertainty_figures.py"), "--data", str(data),
            "--train-episodes", "4", "--steps", "14", "--image-size", "16", "--members", "2", "--epochs", "1",
            "--ood-train-episodes", "2", "--ood-test-episodes", "1", "--ood-epochs", "1", "--ood-image-size", "16",
            "--palette", "per-shape", "--threads", "1", "--skip", "bench", "--json", str(out)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads(out.read_text())
    assert figures["main"]["palette"] == figures["ood"]["palette"] == "per-shape"
    assert figures["main"]["h1_mse"] > 0 and -1 <= figures["main"]["spearman"] <= 1
    assert set(figures["ood"]["disagreement_ratio_to_heldout_T"]) == {"box", "L", "disk", "T_train"}
    assert "palette" in Catalog(data).eval_split().params  # the recoloured world is pinned with the split


def test_chaos_loses_nothing_acknowledged_through_service_and_worker_kills(tmp_path):
    data, out = tmp_path / "data", tmp_path / "chaos.json"
    argv = [sys.executable, str(ROOT / "bench" / "chaos.py"), "--data", str(data), "--requests", "12",
            "--kills", "2", "--worker-kills", "1", "--steps", "5", "--realtime", "4", "--seed", "1",
            "--json", str(out)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(out.read_text())
    assert summary["problems"] == []
    assert summary["by_status"] == {"done": 12}
    assert summary["episodes"] == summary["requests"] == 12
    assert summary["service_starts"] >= 2 and summary["worker_kills"] == 1


def test_chaos_refuses_a_non_empty_data_directory(tmp_path):
    (tmp_path / "something").write_text("")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "chaos.py"), "--data", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "not an empty directory" in proc.stderr


@pytest.mark.timeout(300)
def test_soak_keeps_collecting_and_retraining_and_sees_no_leak(tmp_path):
    data, out = tmp_path / "data", tmp_path / "soak.json"
    argv = [sys.executable, str(ROOT / "bench" / "soak.py"), "--data", str(data), "--minutes", "1",
            "--warmup-minutes", "0.3", "--interval", "3", "--size", "16", "--steps", "10", "--eval-episodes", "4",
            "--realtime", "2", "--retrain-every", "8", "--retrain-args",
            "--members 2 --epochs 1 --widths 4,4,4 --batch-size 8 --from-champion --device cpu --min-improvement 0",
            "--json", str(out)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert out.exists(), proc.stderr[-3000:]
    summary = json.loads(out.read_text())
    assert proc.returncode == 0, (summary["problems"], proc.stderr[-3000:])
    assert summary["problems"] == [] and summary["retrain_jobs"] >= 1 and summary["models"].get("champion") == 1
    # after the first champion the active planner chose states (the seeds and top-ups are uniform draws)
    assert summary["requests_by_planner"].get("active", 0) >= 1


def test_zenoh_cap_bench_drops_over_the_cap_and_passes_under_zenohs_default(tmp_path):
    out = tmp_path / "cap.json"
    argv = [sys.executable, str(ROOT / "bench" / "zenoh_cap.py"), "--mb", "70", "--timeout", "5", "--json", str(out)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    assert not result["capped"]["handler_saw_big"] and result["capped"]["small_reply"] == "12"
    assert result["zenoh_default"]["handler_saw_big"] and result["zenoh_default"]["big_reply"] == str(70 << 20)
    assert result["capped"]["receiver_peak_mib_after"] < result["zenoh_default"]["receiver_peak_mib_after"]


@pytest.mark.skipif(__import__("os").geteuid() != 0, reason="needs root (network namespaces)")
def test_upload_parts_bench_stores_both_ways_over_the_veth_pair(tmp_path):
    out = tmp_path / "parts.json"
    argv = [sys.executable, str(ROOT / "bench" / "upload_parts.py"), "--rounds", "1", "--steps", "200",
            "--part-kb", "32", "--json", str(out)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    assert [(r["mode"], r["result"]) for r in result["rounds"]] == [("whole", "stored"), ("parts", "stored")]
    assert result["rounds"][1]["bytes"] > 3 * 32 * 1024 and result["parts_over_whole_upload_s"] > 0


@pytest.mark.parametrize("script, flag", [("soak.py", "--size"), ("uncertainty_figures.py", "--image-size"),
                                          ("uncertainty_figures.py", "--ood-image-size")])
def test_figure_scripts_refuse_a_frame_size_no_model_trains_on_in_one_line(tmp_path, monkeypatch, capsys, script,
                                                                          flag):
    """(The script's ``main`` in this process: its parser is all this runs.)"""
    data = tmp_path / "data"
    monkeypatch.syspath_prepend(str(ROOT / "bench"))  # (soak.py imports its neighbour chaos.py)
    main = importlib.import_module(script.removesuffix(".py")).main
    monkeypatch.setattr(sys, "argv", [script])  # (argparse's prog)
    with pytest.raises(SystemExit) as stopped:
        main(["--data", str(data), flag, "12"])
    assert stopped.value.code == 2
    assert capsys.readouterr().err.splitlines() == [f"{script}: error: argument {flag}: expected a multiple of 8 "
                                                    "from 16 to 1024 (what a model trains on), found 12"]
    assert not data.exists()  # refused before anything was made


UNCERTAINTY_FIGURES_REFUSALS = [
    (["--skip", "foo"], "argument --skip: expected a comma list of main, ood, bench, found 'foo'"),
    (["--skip", "main,ood,bench"], "--skip main,ood,bench leaves no figure to make"),
    (["--members", "1"], "argument --members: expected an ensemble of at least 2 members (one cannot disagree), "
                         "found 1"),
    (["--threads", "0"], "argument --threads: expected a positive integer, found 0"),
    (["--epochs", "0"], "argument --epochs: expected a positive integer, found 0"),
    (["--lr", "nan"], "argument --lr: expected a positive number, found 'nan'"),
    (["--steps", "2"], "argument --steps: expected at least 3 steps (a model learns from 2 frames of context and "
                       "the next one), found 2"),
    (["--bench-threads", "2,x"], "argument --bench-threads: expected a comma list of positive integers such as "
                                 "1,2, found '2,x'"),
    (["--json", "{tmp}/no/such/dir/figures.json"], "argument --json: expected a file in an existing directory, "
                                                  "found no directory {tmp}/no/such/dir"),
    (["--skip", "ood", "--ood-epochs", "3"], "--ood-epochs sets the ood figure, which --skip leaves out"),
    (["--skip", "main,ood", "--steps", "30"], "--steps sets the main and ood figures, which --skip leaves out"),
    (["--skip", "bench", "--bench-threads", "1"], "--bench-threads sets the bench figure, which --skip leaves out"),
    (["--steps", "6"], "--steps 6 is too short for --context 2: the main figure's calibration rolls out 5 steps "
                       "after the context (--steps at least 7)"),
    (["--skip", "main,bench", "--ood-horizon", "49"], "--ood-horizon 49 leaves no step to score in episodes of "
                                                      "--steps 50 (2 context frames first: at most 48)"),
    (["--skip", "main,bench", "--ood-cache", "{tmp}/cache.pt"],
     "--ood-cache {tmp}/cache.pt: not a file torch.save wrote; give another file or remove it"),
]


@pytest.mark.parametrize("flags, message", UNCERTAINTY_FIGURES_REFUSALS)
def test_uncertainty_figures_refuses_bad_flags_in_one_line_before_any_work(tmp_path, monkeypatch, capsys, flags,
                                                                          message):
    """Each bad value or pair of flags that contradict each other: exit 2, one line, nothing collected (the
    --skip typo ran every figure; the rest failed after collecting 80 episodes, or after training).
    The script's own ``main`` in this process: a process each took ~4 s for torch's import (the script's exit path
    is run as a process by the next test)."""
    from bench.uncertainty_figures import main
    data = tmp_path / "data"
    (tmp_path / "cache.pt").write_text("not a checkpoint\n")
    main_flags = [] if "main" in " ".join(flags) else ["--data", str(data)]
    monkeypatch.setattr(sys, "argv", ["uncertainty_figures.py"])  # (argparse's prog)
    with pytest.raises(SystemExit) as stopped:
        main([*main_flags, *(f.format(tmp=tmp_path) for f in flags)])
    out, err = capsys.readouterr()
    assert (stopped.value.code, err.splitlines()) == (2, [f"uncertainty_figures.py: error: "
                                                          f"{message.format(tmp=tmp_path)}"])
    assert out == "" and not data.exists()


def test_uncertainty_figures_needs_data_for_the_main_figure_only_and_explains_every_flag():
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "uncertainty_figures.py"), "--skip", "bench"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr.splitlines()) == (2, ["uncertainty_figures.py: error: --data is required "
                                                               "for the main figure (or --skip main)"])
    from bench.uncertainty_figures import build_parser, check_args
    parser = build_parser()
    assert [a.option_strings for a in parser._actions if not a.help] == []  # --help explains every flag
    for recorded in (["--data", "DIR", "--skip", "main,bench", "--threads", "1", "--ood-epochs", "40"],
                     ["--data", "DIR", "--skip", "main,ood", "--bench-threads", "1,2", "--bench-seconds", "20"]):
        check_args(parser, parser.parse_args(recorded))  # BENCHMARKS.md's commands: --data unused, not refused


def test_uncertainty_figures_refuses_a_data_directory_of_another_eval_split_before_collecting(tmp_path):
    """A data directory whose pinned eval split was made with other settings (here 2 episodes): one line, exit 2,
    nothing added (it was a traceback)."""
    from workers.collect import create_eval_split
    data = tmp_path / "data"
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=2, seed=1234, steps=8, image_size=16)
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "uncertainty_figures.py"), "--data", str(data),
                           "--steps", "8", "--image-size", "16", "--skip", "ood,bench"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert [line.startswith(f"uncertainty_figures.py: error: --data {data}: ") for line in proc.stderr.splitlines()] \
        == [True]
    assert catalog.count(split="train") == 0 and catalog.count(split="eval") == 2


def test_uncertainty_figures_refuses_an_ood_cache_of_other_members_before_the_main_figure(tmp_path):
    import torch
    from uncertainty.ensemble import Ensemble
    from uncertainty.model import PredictorConfig
    cache = tmp_path / "ood.pt"
    torch.save({"weights": Ensemble(PredictorConfig(image_size=16), members=2).state_dict(), "losses": [1.0]}, cache)
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "uncertainty_figures.py"), "--data",
                           str(tmp_path / "data"), "--members", "3", "--ood-cache", str(cache)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr.splitlines()) == (2, [
        f"uncertainty_figures.py: error: --ood-cache {cache}: not the OOD ensemble of --members 3 (its weights "
        "differ in shape); give its --members, or another file"])
    assert not (tmp_path / "data").exists()


OOD_TINY = ["--skip", "main,bench", "--members", "2", "--steps", "8", "--ood-train-episodes", "2",
            "--ood-test-episodes", "1", "--ood-epochs", "1", "--threads", "1"]


def _figures(*flags: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "uncertainty_figures.py"), *OOD_TINY, *flags],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_uncertainty_figures_refuses_an_ood_cache_made_with_other_flags_and_reuses_one_made_with_these(tmp_path):
    """A cache made at --ood-image-size 16 was reused at 32 without a word (the members are convolutional)."""
    cache = tmp_path / "ood.pt"
    made = _figures("--ood-image-size", "16", "--ood-cache", str(cache))
    assert made.returncode == 0 and cache.is_file(), made.stderr[-2000:]
    written = cache.read_bytes()
    other = _figures("--ood-image-size", "32", "--ood-epochs", "2", "--ood-cache", str(cache))
    assert (other.returncode, other.stderr.splitlines()) == (2, [
        f"uncertainty_figures.py: error: --ood-cache {cache}: made with --ood-epochs 1 (not 2), --ood-image-size 16 "
        "(not 32); give the flags it was made with, or another file, or remove it to train again"])
    again = _figures("--ood-image-size", "16", "--ood-cache", str(cache))
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(again.stdout)["ood"]["train_losses"] == json.loads(made.stdout)["ood"]["train_losses"]
    assert cache.read_bytes() == written


def test_uncertainty_figures_refuses_an_ood_cache_that_records_no_flags(tmp_path):
    import torch
    from uncertainty.ensemble import Ensemble
    from uncertainty.model import PredictorConfig
    cache = tmp_path / "ood.pt"
    torch.save({"weights": Ensemble(PredictorConfig(image_size=16), members=2).state_dict(), "losses": [1.0]}, cache)
    proc = _figures("--ood-image-size", "16", "--ood-cache", str(cache))
    assert (proc.returncode, proc.stderr.splitlines()) == (2, [
        f"uncertainty_figures.py: error: --ood-cache {cache}: it does not record the flags it was made with (written "
        "before they were recorded); give another file, or remove it to train again"])


def test_torch_threads_reports_a_failed_timing_process_with_its_stderr(tmp_path):
    """A timing process that fails: its exit status is checked before its output is parsed, its stderr's end
    shown, exit 1 (it was a ValueError from unpacking an empty output). A torch.py in the working directory
    shadows torch in the `python -c` children only (the script itself imports no torch)."""
    (tmp_path / "torch.py").write_text("import sys\nsys.stderr.write('torch broken on purpose\\n')\nsys.exit(3)\n")
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "torch_threads.py"), "--steps", "3"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.splitlines() == ["torch_threads.py: a timing process of 'alone' exited 3; its stderr ends:",
                                        "torch broken on purpose"]
    assert proc.stdout == ""


def test_torch_threads_times_every_setting_and_refuses_no_steps(tmp_path):
    out = tmp_path / "threads.json"
    script = str(ROOT / "bench" / "torch_threads.py")
    proc = subprocess.run([sys.executable, script, "--steps", "3", "--json", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    settings = json.loads(out.read_text())["settings"]
    assert [len(s["seconds"]) for s in settings.values()] == [1, 2, 1, 2, 1, 2]
    assert settings["alone"]["over_alone"] == 1.0 and all(s["over_alone"] > 0 for s in settings.values())
    assert settings["one thread, two at once"]["threads"] == 1
    bad = subprocess.run([sys.executable, script, "--steps", "0"], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert (bad.returncode, bad.stderr.splitlines()) == (2, ["torch_threads.py: error: --steps must be at least 1, "
                                                            "found 0"])  # one line: no usage above it


def _data_with_a_champion(data: Path) -> None:
    """A tiny catalog (eval split, 3 training episodes) and a champion trained on it."""
    import numpy as np
    from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
    from uncertainty.config import TrainConfig
    from uncertainty.train import train_candidate
    from workers.collect import collect_episode, create_eval_split
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=2, seed=1, steps=8, image_size=16)
    for i, r in enumerate(UniformPlanner(UniformPlannerConfig(steps=8), np.random.default_rng(0)).seed(3)):
        catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy, policy_params=r.policy_params,
                                            seed=i, steps=8, image_size=16))
    train_candidate(catalog, ModelRegistry(data), TrainConfig(members=2, widths=(4, 4, 4), batch_size=8, epochs=1,
                                                              device="cpu", progress=False))


@pytest.mark.timeout(300)
def test_scoring_threads_times_each_setting_against_its_alone_figure_and_leaves_the_data_alone(tmp_path):
    data, out = tmp_path / "data", tmp_path / "threads.json"
    script = str(ROOT / "bench" / "scoring_threads.py")
    bad = subprocess.run([sys.executable, script, "--data", str(data)], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "no catalog in" in bad.stderr.splitlines()[-1]
    _data_with_a_champion(data)
    files = lambda: sorted((p.relative_to(data), p.stat().st_size) for p in data.rglob("*")  # noqa: E731
                           if p.is_file() and not p.name.endswith(("-wal", "-shm")))  # (SQLite's, while open)
    before = files()
    proc = subprocess.run([sys.executable, script, "--data", str(data), "--repeats", "1", "--score-seconds", "0.5",
                           "--threads", "1", "--retrain-args", "--members 2 --epochs 1 --widths 4,4,4 --device cpu",
                           "--rate", "2", "--json", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=280)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(out.read_text())
    settings = result["settings"]
    assert len(settings) == 7 and all(len(s["each"]) == 1 for s in settings.values())
    assert settings["retrain alone"]["retrain_over_alone"] == 1.0
    assert settings["scorer alone, 1 threads"] == {**settings["scorer alone, 1 threads"], "threads": 1,
                                                   "scoring_over_alone": 1.0}
    fitted = max(1, result["cores"] - 1)
    both = settings[f"scorer 1 threads, retrain {fitted} (fitted)"]
    assert both["threads"] == 1 and both["retrain_s"] > 0 and both["scored_per_s"] > 0
    assert settings["both default threads"]["threads"] >= 1  # torch's own choice
    scored = [s for s in settings.values() if "scored_per_s" in s]
    assert len(scored) == 5 and result["rate"] == 2.0
    # Paced: one episode every 0.5 s from the start (unpaced, this tiny model scores hundreds a second).
    assert all(0 < s["scored_per_s"] < 10 and 0 <= s["busy_share"] <= 1 for s in scored), scored
    assert files() == before and len(ModelRegistry(data).list()) == 1  # every retrain trained a copy


def test_heap_trim_plays_the_episodes_through_the_planner_in_each_setting(tmp_path):
    data, out = tmp_path / "data", tmp_path / "heap.json"
    script = str(ROOT / "bench" / "heap_trim.py")
    bad = subprocess.run([sys.executable, script, "--data", str(data), "--episodes", "1"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--episodes must be at least 2" in bad.stderr.splitlines()[-1]
    _data_with_a_champion(data)
    proc = subprocess.run([sys.executable, script, "--data", str(data), "--episodes", "3", "--repeats", "1",
                           "--interval", "1000", "--json", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=280)
    assert proc.returncode == 0, proc.stderr[-2000:]
    settings = json.loads(out.read_text())["settings"]
    assert list(settings) == ["no trim", "trim after every episode", "trim at most every 1000 s",
                              "no trim, MALLOC_MMAP_THRESHOLD_=131072"]
    assert all(s["episodes"] == 3 and s["per_s"] > 0 and s["rss_max_mib"] >= s["rss_first_mib"] > 0
               for s in settings.values())
    assert settings["no trim"]["per_s_over_no_trim"] == 1.0
    trims = [s["trims"] for s in settings.values()]
    assert trims in ([0, 3, 1, 0], [0, 0, 0, 0])  # (all 0: a C library without malloc_trim)


def test_calibration_diagnostic_takes_a_version_as_models_show_does(tmp_path, monkeypatch, capsys):
    """An unknown version, a directory that is no data directory and one without a champion: exit 2 in one line
    (they were a traceback, or exit 1); a unique prefix of a version is taken as `models show` takes it. The
    refusals run the script's ``main`` in this process (a process each took ~4 s for torch's import)."""
    from bench.calibration_diagnostic import main
    script, data = str(ROOT / "bench" / "calibration_diagnostic.py"), tmp_path / "data"
    monkeypatch.setattr(sys, "argv", ["calibration_diagnostic.py"])  # (argparse's prog)

    def error(*flags: str) -> tuple[object, list[str]]:
        with pytest.raises(SystemExit) as stopped:
            main(["--data", str(data), *flags])
        return stopped.value.code, capsys.readouterr().err.splitlines()
    prefix = "calibration_diagnostic.py: error:"
    assert error() == (2, [f"{prefix} --data {data}: not a data directory (no catalog.sqlite)"])
    Catalog(data)
    assert error() == (2, [f"{prefix} --data {data}: no champion; give --version"])
    assert error("--version", "m9") == (2, [f"{prefix} unknown model version 'm9'; the registry is empty"])
    _data_with_a_champion(data)
    version = ModelRegistry(data).champion()
    assert error("--version", "m9") == (2, [f"{prefix} unknown model version 'm9'; latest: {version}"])
    proc = subprocess.run([sys.executable, script, "--data", str(data), "--version", version[:7]], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout)["version"] == version


def test_make_bench_keeps_each_benchmarks_whole_json_indented_or_compact():
    from bench.__main__ import _last_json

    result = {"fused": {"frames_per_s": 551.0}, "speedup_per_round": [1.4, 1.5, 1.49], "note": "x"}
    logged = "loading the model\n[info] 3 rounds\n"
    assert _last_json(logged + json.dumps(result, indent=2) + "\n") == result  # not the list's last item
    assert _last_json(logged + json.dumps(result) + "\n") == result
    assert _last_json(json.dumps([{"seed": 0}, {"seed": 1}], indent=1)) == [{"seed": 0}, {"seed": 1}]
    assert _last_json(json.dumps({"a": 1}) + "\n" + json.dumps({"b": 2}, indent=2)) == {"b": 2}
    assert _last_json("no figures\n42\n")["error"] == "no JSON in output"


def test_soak_judges_growth_after_the_first_champion_is_loaded(monkeypatch):
    """A 10-minute soak's default warm-up (2 min) ended before the first champion was loaded (2.8 min), so the
    ~300 MiB step of torch and the model counted as growth and the verdict was a leak."""
    monkeypatch.syspath_prepend(str(ROOT / "bench"))  # (the script imports its neighbour chaos.py)
    from soak import warm_samples
    samples = [{"t_min": t / 4, "models": int(t >= 11)} for t in range(40)]  # a model from 2.75 min
    assert [s["t_min"] for s in warm_samples(samples, 2.0)][0] == 3.0  # not 2.0: after the sample that saw it
    assert warm_samples(samples, 5.0)[0]["t_min"] == 5.0  # a warm-up past the first model stands
    assert warm_samples(samples[:14], 2.0)[0]["t_min"] == 2.0  # too few samples after it: the warm-up alone
    assert warm_samples([{"t_min": t, "models": 0} for t in range(9)], 2)[0]["t_min"] == 2  # no model yet


def test_store_counts_times_the_counts_of_a_long_history_and_refuses_bad_sizes(tmp_path):
    script, out = str(ROOT / "bench" / "store_counts.py"), tmp_path / "counts.json"
    bad = subprocess.run([sys.executable, script, "--repeats", "0"], cwd=ROOT, capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and "--repeats and --cycles at least 1" in bad.stderr.splitlines()[-1]
    proc = subprocess.run([sys.executable, script, "--rows", "50", "--repeats", "2", "--cycles", "20", "--json",
                           str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads(out.read_text())
    assert (figures["rows"], figures["repeats"], figures["cycles"]) == (50, 2, 20)
    assert all(figures[k] > 0 for k in ("count_split_ms", "count_split_rows_ms", "read_stores_ms", "queue_counts_ms",
                                        "queue_counts_rows_ms", "complete_per_s_kept", "release_per_s_bare"))


@pytest.mark.parametrize("bad", [["--rounds", "0"], ["--seconds", "0"], ["--seconds", "nan"], ["--size", "7"]])
def test_sim_vs_pusht_refuses_a_bad_setting_before_it_installs_or_runs_anything(bad):
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "sim_vs_pusht.py"), *bad], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "creating" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("sim_vs_pusht.py: error: --rounds must be at least 1")
