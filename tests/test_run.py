"""``activecollect run`` end to end: real service, worker processes over Zenoh, retrain jobs, report.

Tiny settings (16 px frames, 12-step episodes, a 2-member ensemble of 4-channel
layers) so the whole loop fits in a test; the default settings are measured by hand
(see the report of the helper session / BENCHMARKS.md).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from orchestrator.loop import LoopRun, worker_command
from orchestrator.loopconfig import RunConfig
from storage.catalog import Catalog
from storage.models import ModelRegistry
from storage.queue import RequestQueue
from storage.requests import RequestStatus
from uncertainty.config import MAX_EPOCHS
from tests.conftest import REPO, alive, children, holds, wait_for
from tests.orchestrator import conftest as orchestrator_fixtures
from tests.orchestrator.test_service import new_request

make_service = orchestrator_fixtures.make_service  # its in-process service, for a test below too

TINY = ["--round", "4", "--workers", "2", "--steps", "12", "--image-size", "16", "--eval-episodes", "4",
        "--dashboard-port", "0", "--no-progress", "--retrain-args",
        "--members 2 --epochs 2 --widths 4,4,4 --batch-size 8 --from-champion --device cpu --min-improvement 0"]

#: ``activecollect run`` whose workers pace their episodes (``--realtime 1``: 30 steps last 3 s), so each holds
#: one when the run is stopped. argv: DATA_DIR
PACED_RUN = """
import json, sys
from orchestrator.loop import LoopRun, worker_command
from orchestrator.loopconfig import RunConfig
from workers.collect import create_eval_split
cfg = RunConfig(data_dir=sys.argv[1], budget=400, round_episodes=40, steps=30, image_size=16, eval_episodes=1,
                dashboard_port=-1, progress=False)
run = LoopRun(cfg, lambda catalog, n, seed, steps, size: create_eval_split(catalog, n, seed, steps, size),
              worker_cmd=lambda *args: worker_command(*args) + ["--realtime", "1"])
print(json.dumps(run.run().to_json()), flush=True)
"""


def run_cmd(data: Path, budget: int) -> list[str]:
    return [sys.executable, "-m", "orchestrator", "run", "--data", str(data), "--budget", str(budget), "--json",
            *TINY]


def train_count(data: Path) -> int:
    if not (data / "catalog.sqlite").exists():
        return 0
    return Catalog(data).count(split="train")


def leased_by_each(queue: RequestQueue, workers: int, logs: Path) -> list:
    """The leased requests once each of ``workers`` holds one, in hand by its log (``logs``/ID.log: a worker signalled
    while the grant is on its way gives the request back, rightly); [] before."""
    leased = queue.list(status="leased")
    if len({r.worker_id for r in leased}) != workers:
        return []
    in_hand = all(holds((logs / f"{r.worker_id}.log").read_text(errors="replace"), r.id) for r in leased)
    return leased if in_hand else []


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_run_collects_retrains_promotes_reports_and_resumes_after_ctrl_c(tmp_path):
    data = tmp_path / "data"
    # 1. a run interrupted with Ctrl-C (SIGINT to its process group, as a terminal sends it; the suite's
    # children start with SIGINT's default disposition, conftest.sigint_as_in_a_terminal); its budget is more
    # than it can reach before the signal, so it cannot end on its own first
    first = subprocess.Popen(run_cmd(data, 400), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True)
    try:
        wait_for(lambda: train_count(data) >= 4, 240, "the first round of episodes")
        os.killpg(first.pid, signal.SIGINT)
        out, err = first.communicate(timeout=120)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 130, f"{err[-2000:]}\n{out[-2000:]}"
    interrupted = json.loads(out)
    assert interrupted["interrupted"] is True and Path(interrupted["report"]).exists()
    # nothing acknowledged is lost: every done request has its episode in the catalog, nothing is leased
    catalog = Catalog(data)
    queue = RequestQueue(catalog.db_path)
    done = queue.list(status="done")
    assert done and all(catalog.get(r.episode_id).request_id == r.id for r in done)
    assert queue.counts()["leased"] == 0
    queue.close()
    kept = train_count(data)

    # 2. the next run resumes from the catalog and finishes the budget
    budget = max(12, kept + 4)
    second = subprocess.run(run_cmd(data, budget), capture_output=True, text=True, timeout=540)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "dashboard at http://127.0.0.1:" in second.stderr  # --dashboard-port 0: the operator must learn where
    result = json.loads(second.stdout)
    assert result["interrupted"] is False
    assert budget <= result["episodes"] <= budget + 2 and result["episodes"] >= kept
    assert train_count(data) == result["episodes"]

    registry = ModelRegistry(data)
    champion = registry.champion()
    assert champion is not None and result["champion"] == champion
    trained_on = sorted(int(m.metrics["train_episodes"]) for m in registry.list())
    assert trained_on[-1] == result["episodes"]  # the last retrain saw the whole budget
    assert any(r["status"] in ("promoted", "rejected") for r in result["retrains"])

    # the rounds after the first model were planned by it (active requests with their reasons)
    queue = RequestQueue(catalog.db_path)
    reasons = [r.reason for r in queue.list(status="done")]
    active = [r for r in reasons if r.get("planner") == "active"]
    assert active, f"no active requests among {sorted({r.get('planner') for r in reasons})}"
    assert all(r["model_version"] in {m.version for m in registry.list()} and r["score"] > 0 for r in active)
    queue.close()

    report = Path(result["report"])
    assert report.name == "index.html" and report.parent.parent == data / "reports"
    html = report.read_text()
    for png in ("curve.png", "disagreement.png", "frames.png"):
        assert png in html and (report.parent / png).read_bytes().startswith(b"\x89PNG")
    summary = json.loads((report.parent / "summary.json").read_text())
    assert summary["summary"]["episodes"] == result["episodes"] and summary["curve"]
    with sqlite3.connect(data / "catalog.sqlite") as conn:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


@pytest.mark.slow
@pytest.mark.timeout(120)
@pytest.mark.parametrize("when, extra", [
    ("collecting", ["--round", "40"]),  # a long first round: the workers hold episodes when it comes
    ("retraining", ["--retrain-args", f"--members 2 --epochs {MAX_EPOCHS} --widths 4,4,4 --device cpu"]),  # ~forever
])
def test_sigterm_stops_a_run_as_ctrl_c_does(tmp_path, when, extra):
    """SIGTERM to `run` alone (kill, timeout, systemd, a CI runner): no lease is left held, a running retrain job is
    stopped, the report is written, and nothing it started outlives it. (That the workers upload the episodes in
    hand rather than give them back is shown with paced workers by
    test_a_worker_stopped_both_by_its_run_and_by_a_signal_to_the_group_uploads_its_episode.)"""
    data = tmp_path / "data"
    run = subprocess.Popen(run_cmd(data, 400) + extra, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           start_new_session=True)
    try:
        if when == "collecting":  # the first round's requests are leased: episodes in hand
            wait_for(lambda: run.poll() is not None or train_count(data) >= 1, 60, "the first uploads")
        else:
            wait_for(lambda: run.poll() is not None or any(" retrain " in c for c in children(run.pid).values()), 60,
                     "the first retrain job")
        assert run.poll() is None, run.communicate()  # (a run that refused its flags: say why, not wait 60 s)
        started = children(run.pid)
        assert sum("workers.agent" in c for c in started.values()) == 2, started
        run.send_signal(signal.SIGTERM)
        out, err = run.communicate(timeout=60)
        survivors = [c for pid, c in started.items() if alive(pid)]
    finally:
        with contextlib.suppress(ProcessLookupError):  # what outlived the run (its process group)
            os.killpg(run.pid, signal.SIGKILL)
        run.wait()
    assert run.returncode == 130, f"{err[-3000:]}\n{out[-2000:]}"  # as Ctrl-C: interrupted
    result = json.loads(out)
    assert result["interrupted"] is True and Path(result["report"]).is_file()
    assert survivors == []
    if when == "retraining":
        assert [r["status"] for r in result["retrains"]] == ["killed"]
    catalog = Catalog(data)
    queue = RequestQueue(catalog.db_path)
    try:
        assert queue.counts()["leased"] == 0  # every episode in hand was uploaded (or its lease given back)
        done = queue.list(status="done")
        assert done and all(catalog.get(r.episode_id).request_id == r.id for r in done)
    finally:
        queue.close()


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_sigterm_to_the_whole_process_group_lets_every_worker_upload_the_episode_in_hand(tmp_path):
    """systemd (KillMode=control-group) or `kill -TERM -PGID`: run and its workers get SIGTERM at once. Run's own
    stop must not be a worker's second signal (which gives the episode back unfinished): every episode in hand
    is uploaded."""
    data = tmp_path / "data"
    run = subprocess.Popen([sys.executable, "-c", PACED_RUN, str(data)], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True, cwd=REPO, start_new_session=True)
    try:
        wait_for(lambda: (data / "logs" / "run-w1.log").exists(), 60, "the run's workers")  # (after its queue)
        queue = RequestQueue(data / "catalog.sqlite")
        held = wait_for(lambda: leased_by_each(queue, 2, data / "logs"), 60, "an episode in each worker's hands")
        os.killpg(run.pid, signal.SIGTERM)
        out, err = run.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):  # what outlived the run (its process group)
            os.killpg(run.pid, signal.SIGKILL)
        run.wait()
    assert run.returncode == 0 and json.loads(out)["interrupted"] is True, err[-3000:]
    logs = {p.name: p.read_text() for p in (data / "logs").glob("run-w*.log")}
    try:
        for request in held:  # uploaded, not given back
            done = queue.get(request.id)
            assert (done.status, done.token, done.attempts) == (RequestStatus.DONE, request.token, 0), logs
        assert queue.counts()["leased"] == 0
        assert not [r.id for r in queue.list(status="queued") if r.token], logs  # nothing else was given back
    finally:
        queue.close()
    assert not [name for name, text in logs.items() if "INFO released " in text or "stopping now" in text], logs


@pytest.mark.parametrize("first", ["the group's SIGTERM", "run's stop"])
def test_a_worker_stopped_both_by_its_run_and_by_a_signal_to_the_group_uploads_its_episode(
        make_service, endpoint, namespace, tmp_path, first):
    """Whichever reaches a worker first, run's stop (its tear-down) and a SIGTERM to the whole group (systemd,
    `kill -TERM -PGID`) are one stop, not two: the worker finishes and uploads the episode in hand."""
    service = make_service()
    for _ in range(4):
        service.queue.enqueue(new_request(steps=30))  # 3 s of paced collection each
    run = LoopRun(RunConfig(data_dir=tmp_path / "run", dashboard_port=-1, progress=False), lambda *args: "")
    logs = [tmp_path / f"run-w{i}.log" for i in range(2)]
    for i, log in enumerate(logs):  # as run starts them, pacing their episodes
        cmd = worker_command(endpoint, namespace, f"run-w{i}", 16) + ["--realtime", "1"]
        with open(log, "wb") as out:
            run.procs.append(subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                              cwd=REPO))
    teardown = threading.Thread(target=run._teardown, kwargs={"interrupted": True})
    try:
        held = wait_for(lambda: leased_by_each(service.queue, 2, tmp_path), 30, "an episode in each worker's hands")
        if first == "run's stop":
            teardown.start()
            wait_for(lambda: all("draining" in log.read_text() for log in logs), message="the workers to drain")
        for p in run.procs:
            p.send_signal(signal.SIGTERM)
        if first == "the group's SIGTERM":
            wait_for(lambda: all("draining" in log.read_text() for log in logs), message="the workers to drain")
            teardown.start()
        teardown.join(60)
    finally:
        for p in run.procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    texts = [log.read_text() for log in logs]
    assert [p.returncode for p in run.procs] == [0, 0], texts
    for request in held:  # uploaded, not given back
        done = service.queue.get(request.id)
        assert (done.status, done.attempts) == (RequestStatus.DONE, 0), texts
    assert service.queue.counts()["leased"] == 0
    assert not [r.id for r in service.queue.list(status="queued") if r.token], texts  # nothing was given back


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_run_whose_every_retrain_failed_exits_1_saying_so(tmp_path):
    """Every retrain fails (here: the eval split's file is lost, so no candidate can be evaluated): no retrain of
    the run trains a model, so the run did not do its job, whatever it collected. A retrain that fails is not
    tried again and again: each round's is tried once. (One that found another retrain holding the lock waits
    for it: tests/test_run_stops_and_resumes.py.)"""
    from workers.collect import create_eval_split
    data = tmp_path / "data"
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=1, seed=RunConfig.eval_seed, steps=3, image_size=16)
    lost = catalog.list(split="eval")[0]
    lost.path.unlink()
    proc = subprocess.run([sys.executable, "-m", "orchestrator", "run", "--data", str(data), "--budget", "4",
                           "--round", "2", "--workers", "1", "--steps", "3", "--image-size", "16",
                           "--eval-episodes", "1", "--dashboard-port", "-1", "--no-progress", "--retrain-args",
                           "--members 2 --epochs 1 --widths 4,4,4 --device cpu"],
                          capture_output=True, text=True, timeout=360)
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "done: 4 episodes (4 collected by this run), 2 retrains (2 failed)" in proc.stdout, proc.stdout
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("activecollect run: every retrain of this run failed (2 failed; the last: ") and \
        f"file of episode {lost.episode_id} is missing" in last and last.endswith(f"their logs are in {data / 'logs'}")
    assert train_count(data) == 4  # what it collected is kept
    # the report is written without the lost eval episode's frames
    assert f"episode {lost.episode_id} left out of the report: " in proc.stderr


def test_ctrl_c_during_set_up_ends_the_run_with_a_report(tmp_path):
    """A Ctrl-C while the eval split is collected (set-up's slow part): no traceback, a result saying so."""
    def interrupted_eval_split(catalog, episodes, seed, steps, size):
        raise KeyboardInterrupt

    run = LoopRun(RunConfig(data_dir=tmp_path / "data", budget=4, round_episodes=2, image_size=16, steps=8,
                            eval_episodes=2, dashboard_port=-1, progress=False), interrupted_eval_split)
    result = run.run()
    assert result.interrupted and result.episodes == 0 and result.retrains == [] and result.report.is_file()
    html = result.report.read_text()
    assert "<th>queue</th><td>queued=0 leased=0 " in html and "{" not in html.split("<th>queue</th>")[1][:80]


def test_the_run_holds_its_data_directory_until_its_report_is_written(tmp_path, monkeypatch):
    """A `serve` started as a run ends must not run beside the report's writing: the run lets DATA/service.lock go
    after the report, not when its service stops."""
    import orchestrator.loop
    real, held = orchestrator.loop.write_report, []

    def watched(data_dir, inputs):
        held.append(not _free(data_dir / "service.lock"))
        return real(data_dir, inputs)

    monkeypatch.setattr(orchestrator.loop, "write_report", watched)

    def interrupted_eval_split(catalog, episodes, seed, steps, size):
        raise KeyboardInterrupt

    data = tmp_path / "data"
    result = LoopRun(RunConfig(data_dir=data, budget=4, round_episodes=2, image_size=16, steps=8, eval_episodes=2,
                               dashboard_port=-1, progress=False), interrupted_eval_split).run()
    assert result.report.is_file() and held == [True]
    assert _free(data / "service.lock")


def test_sigterm_during_set_up_ends_the_run_with_a_report(tmp_path):
    """SIGTERM while the eval split is collected: the run goes no further (no worker started), reports, and
    gives SIGTERM back to whoever had it."""
    caught: list[int] = []

    def ours(signum, frame):  # what SIGTERM does outside the run (here: not end the test's process)
        caught.append(signum)

    before = signal.signal(signal.SIGTERM, ours)

    def terminated_eval_split(catalog, episodes, seed, steps, size):
        os.kill(os.getpid(), signal.SIGTERM)
        wait_for(lambda: run._terminated.is_set() or caught, message="the run to take the SIGTERM")
        return ""

    try:
        run = LoopRun(RunConfig(data_dir=tmp_path / "data", budget=4, round_episodes=2, image_size=16, steps=8,
                                eval_episodes=2, dashboard_port=-1, progress=False), terminated_eval_split)
        result = run.run()
        mine = signal.getsignal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, before)
    assert caught == [] and mine is ours
    assert result.interrupted and result.episodes == 0 and result.report.is_file() and run.procs == []


def test_a_catalog_with_episodes_of_another_size_still_gets_its_report(tmp_path, monkeypatch):
    """Catalogs from before the one-frame-size rule may mix sizes: the report shows the run's own."""
    import numpy as np
    import storage.catalog
    from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
    from uncertainty.config import TrainConfig
    from uncertainty.train import train_candidate
    from workers.collect import collect_episode, create_eval_split
    monkeypatch.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)
    data = tmp_path / "data"
    catalog = Catalog(data)
    create_eval_split(catalog, episodes=2, seed=RunConfig.eval_seed, steps=8, image_size=16)
    planner = UniformPlanner(UniformPlannerConfig(steps=8), np.random.default_rng(0))
    for i, (r, size) in enumerate(zip(planner.seed(3), (16, 16, 24))):
        if size == 24:  # a champion first (the trainer refuses a mixed catalog), whose report scores episodes
            train_candidate(catalog, ModelRegistry(data), TrainConfig(members=2, widths=(4, 4, 4), batch_size=8,
                                                                      epochs=1, device="cpu", progress=False))
        catalog.add_episode(collect_episode(start_state=r.start_state, policy=r.policy, policy_params=r.policy_params,
                                            seed=i, steps=8, image_size=size))
    run = LoopRun(RunConfig(data_dir=data, budget=3, round_episodes=3, image_size=16, steps=8, eval_episodes=2,
                            dashboard_port=-1, progress=False),
                  lambda catalog, episodes, seed, steps, size: create_eval_split(catalog, episodes, seed, steps, size))
    result = run.run()
    assert not result.interrupted and result.episodes == 3 and result.report.is_file()


def test_the_report_shows_no_other_models_frames_when_the_champion_cannot_be_loaded(tmp_path):
    """The last promotion's weights are damaged: the scorer keeps the model before it, and the report must not
    show that model's frames under the new champion's name; its summary says why there are none."""
    import time

    from orchestrator.champion import ChampionScorer
    from tests.orchestrator.test_champion import _promoted
    from workers.collect import create_eval_split

    data = tmp_path / "data"
    create_eval_split(Catalog(data), episodes=1, seed=RunConfig.eval_seed, steps=8, image_size=16)
    registry = ModelRegistry(data)
    first = _promoted(registry, 0, 0.02)
    run = LoopRun(RunConfig(data_dir=data, budget=1, round_episodes=1, image_size=16, steps=8, eval_episodes=1,
                            dashboard_port=-1, progress=False), create_eval_split)
    run.scorer = ChampionScorer(data)
    assert run.scorer.reload() == first
    second = _promoted(registry, 1, 0.01)
    weights = registry.get(second).weights_path
    weights.write_bytes(weights.read_bytes()[:-7])

    result = run._finish(time.time(), interrupted=False)
    assert result.champion == second and run.scorer.version == first
    summary = json.loads((result.report.parent / "summary.json").read_text())["summary"]
    assert summary["champion_problem"].startswith(f"cannot load champion {second}: ")
    assert not (result.report.parent / "frames.png").exists()
    html = result.report.read_text()
    assert "frames.png" not in html and "<th>champion cannot be loaded</th>" in html  # (the row's label)
    assert f"The champion, {second}, cannot be loaded, so the disagreement map and the predicted-vs-real" in html

    weights_ok = _promoted(registry, 2, 0.005)  # a loadable champion: its frames, and no problem
    result = run._finish(time.time(), interrupted=False)
    assert result.champion == weights_ok and (result.report.parent / "frames.png").is_file()
    assert "champion_problem" not in json.loads((result.report.parent / "summary.json").read_text())["summary"]


def test_a_run_whose_every_worker_died_exits_1_in_one_line(tmp_path, monkeypatch, capsys):
    """Every worker process exits at once (here: a command that fails): the run stops what it started and says so
    in one line, exit 1 (it was a LoopError traceback)."""
    import orchestrator.loop
    from tests.conftest import run_cli
    monkeypatch.setattr(orchestrator.loop, "worker_command",
                        lambda *args: [sys.executable, "-c", "raise SystemExit(3)"])
    data = tmp_path / "data"
    rc, out, err = run_cli(capsys, "run", "--data", str(data), "--budget", "4", "--round", "2", "--workers", "2",
                           "--steps", "3", "--image-size", "16", "--eval-episodes", "1", "--dashboard-port", "-1",
                           "--no-progress")
    assert rc == 1 and out == "", out
    last = err.strip().splitlines()[-1]
    assert last == f"activecollect run: all 2 workers exited (codes [3, 3]); see {data / 'logs'}", err[-2000:]
    assert "Traceback" not in err
    assert not (data / "service.lock").exists() or _free(data / "service.lock")  # the service let the directory go


def _free(lock: Path) -> bool:
    import fcntl
    with open(lock, "rb") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        return True


def _descriptors_on(path: Path) -> int:
    """How many of this process's file descriptors are open on ``path``."""
    fds = Path("/proc/self/fd")
    return sum(1 for fd in fds.iterdir() if _link(fd) == str(path))


def _link(fd: Path) -> str:
    try:
        return os.readlink(fd)
    except OSError:  # (closed meanwhile, the listing's own)
        return ""


def test_the_runs_dashboard_metrics_leave_no_connection_open_per_request(tmp_path):
    """The dashboard answers each request on a thread of its own: /metrics read the run's queue there, which kept
    each thread's SQLite connection (its descriptors) open until the run ended: hours of scraping used them up."""
    import urllib.request

    from storage.database import DB_NAME

    db, seen = tmp_path / "data" / DB_NAME, {}

    def announce(line: str) -> None:
        url, before = line.removeprefix("dashboard at "), _descriptors_on(db)
        for _ in range(20):
            with urllib.request.urlopen(url + "metrics", timeout=30) as reply:
                seen["body"] = reply.read().decode()
        seen["open"] = (before, _descriptors_on(db))
        raise KeyboardInterrupt  # (done: the run stops as on Ctrl-C)

    result = LoopRun(RunConfig(data_dir=tmp_path / "data", budget=4, round_episodes=2, image_size=16, steps=8,
                               eval_episodes=2, dashboard_port=0, progress=False), lambda *args: "",
                     announce=announce).run()
    assert result.interrupted and "activecollect_queue_depth" in seen["body"]
    before, after = seen["open"]
    assert before > 0 and after == before, seen["open"]
