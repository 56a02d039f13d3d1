"""``bench loop --jobs``: the arms in processes of their own give the figures of one process, an arm whose process
dies stops the run with its name, Ctrl-C stops them all, and they die with the command; a stopped run summarises
the rounds its arms had finished; the model's size and schedule reach the config."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from orchestrator.cli.collect import make_eval_split
from orchestrator.cli.loopbench import bench_collect
from orchestrator.loopbench import ARM_POINTS, ArmFailed, LoopBenchConfig, run_bench
from tests.conftest import REPO, alive, children, run_cli, wait_for
from uncertainty.config import TrainConfig

TINY = ("--seeds", "2", "--budget", "4", "--round", "2", "--steps", "12", "--image-size", "16", "--epochs", "1",
        "--members", "2", "--json")


@pytest.fixture
def torch_threads():
    """Leaves torch's thread count as it found it (``--threads`` sets it in this process with one job)."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _figures(summary: dict) -> list[dict]:
    return [{k: v for k, v in p.items() if k != "train_s"} for p in summary["points"]]


def test_arms_in_their_own_processes_give_the_figures_of_one_process(tmp_path, capsys, torch_threads):
    """... and so do arms that take only deterministic algorithms (``--deterministic``: on the CPU torch's kernels
    are deterministic already)."""
    rc, stdout, err = run_cli(capsys, "bench", "loop", *TINY, "--jobs", "3", "--threads", "1", "--widths", "4,8,8",
                              "--batch-size", "8", "--lr", "0.002", "--deterministic", "--out", str(tmp_path / "apart"))
    assert rc == 0, err
    apart = json.loads(stdout)
    rc, stdout, err = run_cli(capsys, "bench", "loop", *TINY, "--threads", "1", "--widths", "4,8,8",
                              "--batch-size", "8", "--lr", "0.002", "--out", str(tmp_path / "here"))
    assert rc == 0, err
    here = json.loads(stdout)
    assert (apart["jobs"], apart["threads"], here["jobs"], here["threads"]) == (3, 1, 1, 1)
    assert apart["config"]["train"]["widths"] == [4, 8, 8] and apart["config"]["train"]["batch_size"] == 8
    assert apart["config"]["train"]["lr"] == 0.002
    assert (apart["config"]["deterministic"], here["config"]["deterministic"]) == (True, False)
    assert [(p["seed"], p["arm"], p["episodes"]) for p in apart["points"]] == [
        (s, a, e) for s in (0, 1) for a in ("active", "uniform") for e in (2, 4)]
    assert _figures(apart) == _figures(here)
    assert all(-1 <= p["spearman"] <= 1 for p in apart["points"])  # each retrain's calibration on the eval split
    assert apart["h1"] == here["h1"] and apart["h5"] == here["h5"]
    assert (tmp_path / "apart" / "seed1" / "uniform" / ARM_POINTS).is_file()


def _collect_dying_in_seed_1(request, seed, image_size, palette=None):
    """``bench_collect``, but the process collecting for seed 1 is killed (SIGKILL) on its first episode."""
    if seed >= 1_000_003:  # run_arm's policy seeds: seed * 1_000_003 + episodes collected
        os.kill(os.getpid(), signal.SIGKILL)
    return bench_collect(request, seed, image_size, palette)


def test_an_arm_whose_process_is_killed_stops_the_run_with_its_name(tmp_path):
    """... and what the other arms had finished is summarised (two jobs: seed 0's arms finish before seed 1's
    start)."""
    cfg = LoopBenchConfig(seeds=(0, 1), budget=4, round_episodes=2, steps=12, image_size=16,
                          train=TrainConfig(members=2, epochs=1, batch_size=8, widths=(4, 8, 8), device="cpu",
                                            progress=False, min_rel_improvement=0.0))
    with pytest.raises(ArmFailed, match=r"the (active|uniform) arm of seed 1 failed \(exit code -9\)") as failed:
        run_bench(cfg, tmp_path / "o", _collect_dying_in_seed_1, make_eval_split, jobs=2, threads=1)
    assert not list((tmp_path / "o").glob("seed1/*/" + ARM_POINTS))
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary == json.loads(json.dumps(failed.value.summary))
    assert (summary["interrupted"], summary["stopped_by"], summary["failure"]) == (True, "failure", str(failed.value))
    assert [(p["seed"], p["arm"], p["episodes"]) for p in summary["points"]] == [
        (0, a, e) for a in ("active", "uniform") for e in (2, 4)]
    assert [r["seed"] for r in summary["h1"]["per_seed"]] == [0] and summary["h1"]["headline"]["budget"] == 4


def _collect_checking_determinism(request, seed, image_size, palette=None):
    """``bench_collect``, in an arm that must take only deterministic algorithms (and a CUDA run's cuBLAS too)."""
    assert torch.are_deterministic_algorithms_enabled() and os.environ.get("CUBLAS_WORKSPACE_CONFIG") == ":4096:8"
    assert not torch.backends.cudnn.benchmark
    return bench_collect(request, seed, image_size, palette)


@pytest.fixture
def determinism_restored(monkeypatch):
    """Leaves torch's determinism and the cuBLAS setting as it found them (one job sets them in this process)."""
    before = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    yield
    torch.use_deterministic_algorithms(before[0], warn_only=before[1])


@pytest.mark.parametrize("jobs", [1, 2])
def test_deterministic_arms_take_only_deterministic_algorithms(tmp_path, jobs, determinism_restored, torch_threads):
    cfg = LoopBenchConfig(seeds=(0,), budget=4, round_episodes=2, steps=12, image_size=16, deterministic=True,
                          train=TrainConfig(members=2, epochs=1, batch_size=8, widths=(4, 8, 8), device="cpu",
                                            progress=False, min_rel_improvement=0.0))
    summary = run_bench(cfg, tmp_path / "o", _collect_checking_determinism, make_eval_split, log=lambda line: None,
                        jobs=jobs, threads=1)
    assert len(summary["points"]) == 4 and summary["config"]["deterministic"] is True


def _start_arms(tmp_path: Path) -> tuple[subprocess.Popen, set[int]]:
    """``bench loop --jobs 2`` in a session of its own, once both arms of seed 0 run: (the command, its children)."""
    # Rounds of 1,000 episodes: minutes of collecting before the first retrain, so that arms left running (or
    # waited for) would keep the command from exiting within the test's time.
    cmd = [sys.executable, "-m", "orchestrator", "bench", "loop", "--seeds", "1", "--budget", "2000", "--round", "1000",
           "--steps", "40", "--image-size", "16", "--jobs", "2", "--threads", "1", "--out", str(tmp_path / "o")]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        # both arms of seed 0 started: they made their catalogs (and the spawn's resource tracker is a child too)
        wait_for(lambda: len(list((tmp_path / "o").glob("seed0/*/catalog.sqlite"))) == 2, timeout=120,
                 message="both arms' catalogs")
        return proc, set(wait_for(lambda: children(proc.pid), message="the arms' processes"))
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise


def _stop(proc: subprocess.Popen, sig: int, group: bool) -> tuple[str, str]:
    """``sig`` to the command (to its whole group, as a terminal's Ctrl-C, if ``group``): its output once it exits.
    Killed with its group if it has not within 60 s."""
    try:
        (os.killpg if group else os.kill)(proc.pid, sig)
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_ctrl_c_stops_every_arm_and_exits_130(tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) while the arms run: the command exits 130 and
    no arm's process is left running."""
    proc, arms = _start_arms(tmp_path)
    _, err = _stop(proc, signal.SIGINT, group=True)
    assert proc.returncode == 130, err
    assert "activecollect: interrupted" in err and "KeyboardInterrupt" not in err
    wait_for(lambda: not any(alive(pid) for pid in arms), timeout=30, message="every arm's process gone")
    assert not (tmp_path / "o" / "summary.json").exists()


@pytest.mark.parametrize("sig, returncode", [(signal.SIGTERM, 128 + signal.SIGTERM), (signal.SIGKILL, -signal.SIGKILL)])
def test_the_arms_die_with_the_command_when_it_alone_is_stopped_or_killed(tmp_path, sig, returncode):
    """A SIGTERM to the command's process alone (a supervisor's stop, `kill PID`) stops its arms as Ctrl-C does; a
    SIGKILL leaves it no chance to: they die with it instead of training on as orphans."""
    proc, arms = _start_arms(tmp_path)
    try:
        _, err = _stop(proc, sig, group=False)
        assert proc.returncode == returncode, err
        assert sig == signal.SIGKILL or "activecollect: interrupted (SIGTERM): no round had finished" in err
        wait_for(lambda: not any(alive(pid) for pid in arms), timeout=30, message="every arm's process gone")
    finally:
        for pid in arms:  # (a failing run's orphans, so that they do not outlive the test)
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("args, message", [
    (("--jobs", "0"), "argument --jobs: expected a positive integer, found 0"),
    (("--threads", "-1"), "argument --threads: expected an integer >= 0, found -1"),
    (("--widths", "8,16"), "argument --widths: expected three positive integers like 8,16,32, found '8,16'"),
    (("--batch-size", "0"), "argument --batch-size: expected a positive integer, found 0"),
])
def test_bench_loop_refuses_bad_jobs_threads_and_model_sizes(tmp_path, capsys, args, message):
    rc, _, err = run_cli(capsys, "bench", "loop", *args, "--out", str(tmp_path / "o"))
    assert rc == 2 and message in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_stopped_run_summarises_the_rounds_its_arms_had_finished(tmp_path, jobs):
    """SIGTERM (a timeout's, a supervisor's) to a run whose arms have finished rounds: exit 143, and summary.json
    holds every point the arms had written, marked interrupted, the comparison over the rounds both arms of the
    seed finished (with one job, the active arm's alone: the uniform arm had not started)."""
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "orchestrator", "bench", "loop", "--seeds", "1", "--budget", "2000", "--round", "2",
           "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2", "--jobs", str(jobs),
           "--threads", "1", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    arms = ("active", "uniform")[:jobs]
    try:
        wait_for(lambda: all((out / "seed0" / arm / ARM_POINTS).exists() for arm in arms), timeout=120,
                 message="a finished round in each running arm")
    finally:
        stdout, err = _stop(proc, signal.SIGTERM, group=False)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert f"activecollect: interrupted (SIGTERM): the finished rounds are in {out / 'summary.json'}" in err
    assert "leaked" not in err and "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["interrupted"], summary["stopped_by"]) == (True, "SIGTERM")
    written = [p for arm in ("active", "uniform") if (out / "seed0" / arm / ARM_POINTS).exists()
               for p in json.loads((out / "seed0" / arm / ARM_POINTS).read_text())]
    assert summary["points"] == written and {p["arm"] for p in written} == set(arms)
    last = {arm: max(p["episodes"] for p in written if p["arm"] == arm) for arm in arms}
    if jobs == 1:
        assert summary["h1"]["headline"] is None and "h1: no seed has a round that both arms finished" in stdout
    else:
        assert summary["h1"]["headline"]["budget"] == min(last.values())
        assert [r["seed"] for r in summary["h1"]["per_seed"]] == [0]
        assert "stopped by SIGTERM: the comparison covers the rounds both arms of a seed finished" in stdout
    assert (out / "loop.png").is_file()


def test_a_killed_run_is_summarised_afterwards_from_its_arms_points(tmp_path, capsys):
    """SIGKILL to the whole run (an out-of-memory kill, the machine lost) once its arms have finished rounds: no
    summary, but `bench loop-summary DIR` writes the one a stopped run writes, from the configuration and points it
    left, marked rebuilt."""
    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "orchestrator", "bench", "loop", "--seeds", "1", "--budget", "2000", "--round", "2",
           "--steps", "12", "--image-size", "16", "--epochs", "1", "--members", "2", "--jobs", "2",
           "--threads", "1", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_for(lambda: all((out / "seed0" / arm / ARM_POINTS).exists() for arm in ("active", "uniform")),
                 timeout=120, message="a finished round in each arm")
    finally:
        _stop(proc, signal.SIGKILL, group=True)
    assert not (out / "summary.json").exists()
    assert json.loads((out / "config.json").read_text())["config"]["budget"] == 2000
    rc, stdout, err = run_cli(capsys, "bench", "loop-summary", str(out))
    assert rc == 0, err
    summary = json.loads((out / "summary.json").read_text())
    written = [p for arm in ("active", "uniform") for p in json.loads((out / "seed0" / arm / ARM_POINTS).read_text())]
    assert summary["points"] == written and (summary["rebuilt"], summary["interrupted"]) == (True, True)
    assert (summary["stopped_by"], summary["seconds"], summary["jobs"], summary["threads"]) == (None, None, 2, 1)
    last = {arm: max(p["episodes"] for p in written if p["arm"] == arm) for arm in ("active", "uniform")}
    assert summary["h1"]["headline"]["budget"] == min(last.values()) and (out / "loop.png").is_file()
    assert "rebuilt from the points the arms wrote" in stdout and "stopped: the comparison covers" in stdout
    rc, stdout, _ = run_cli(capsys, "bench", "loop-summary", "--json", str(out))  # (a rebuilt summary: rebuilt again)
    assert rc == 0 and json.loads(stdout)["points"] == written


HANGS_IN_EXIT = """
import atexit, os, threading, types
import orchestrator.loopbench as loopbench
loopbench.ARM_EXIT_S = 1

def run_arm(*args):
    atexit.register(threading.Event().wait)  # an exit that hangs
    print("ready", flush=True)
    threading.Event().wait()

loopbench.run_arm = run_arm
loopbench._arm_process("active", 0, types.SimpleNamespace(deterministic=False), None, None, None, 1, os.getppid())
"""


def test_a_stopped_arm_whose_exit_hangs_still_ends():
    """A stopped arm exits by SystemExit; one whose exit hangs would, its command SIGKILLed, have nobody left to
    end it. The alarm set with the exit ends it. (An exit lost in a callback is test_signals_callbacks'.)"""
    proc = subprocess.Popen([sys.executable, "-c", HANGS_IN_EXIT], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert proc.stdout.readline() == "ready\n"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == -signal.SIGALRM
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
