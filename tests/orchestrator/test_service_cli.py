"""The operator CLI (queue, workers, stats, watch), ``activecollect worker`` and ``bench dispatch``."""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from orchestrator import dispatchbench
from orchestrator.cli import main
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage.catalog import Catalog
from storage.errors import CatalogUnavailableError
from storage.requests import RequestStatus
from tests.conftest import REPO, free_port, run_cli, wait_for
from tests.orchestrator.test_service import new_request
from workers.agent import WorkerError
from workers.cli import parse_capabilities


@pytest.fixture
def service(data_dir: Path, endpoint: str, namespace: str):
    svc = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,), reap_interval_s=0.1))
    svc.start()
    yield svc
    svc.stop()


@pytest.fixture
def cli(endpoint: str, namespace: str, capsys):
    """Run ``activecollect CMD...`` against the test's service; (exit code, stdout, stderr)."""

    def run(*argv: str) -> tuple[int, str, str]:
        rc = main([*argv, "--connect", endpoint, "--namespace", namespace, "--timeout", "10"])
        out = capsys.readouterr()
        return rc, out.out, out.err

    return run


def test_queue_commands_round_trip(service, cli) -> None:
    rc, out, _ = cli("queue", "add", "--shape", "T", "--seed", "3", "--steps", "7", "--priority", "2",
                     "--idempotency-key", "op-1", "--json")
    assert rc == 0
    added = json.loads(out)
    rid = added["request"]["id"]
    assert added["created"] and added["request"]["steps"] == 7
    rc, out, _ = cli("queue", "add", "--shape", "T", "--seed", "3", "--steps", "7", "--priority", "2",
                     "--idempotency-key", "op-1")
    assert rc == 0 and "already queued" in out  # a retry
    rc, _, err = cli("queue", "add", "--shape", "T", "--idempotency-key", "op-1")
    assert rc == 1 and err.count("\n") == 1 and "bad_field" in err and f"already names request {rid}" in err
    assert "start_state, steps" in err  # a reused key: another start state and length
    rc, out, _ = cli("queue", "ls")
    assert rc == 0 and rid in out and "queued=1" in out
    rc, out, _ = cli("queue", "prioritize", rid, "9.5", "--json")
    assert json.loads(out)["request"]["priority"] == 9.5
    rc, out, _ = cli("queue", "cancel", rid)
    assert rc == 0 and "cancelled" in out
    rc, out, _ = cli("queue", "ls", "--status", "cancelled", "--json")
    assert [r["id"] for r in json.loads(out)["requests"]] == [rid]
    rc, out, _ = cli("queue", "retry", rid)
    assert rc == 0 and service.queue.get(rid).status == RequestStatus.QUEUED
    rc, out, _ = cli("queue", "show", rid)
    assert rc == 0 and '"shape": "T"' in out and "idempotency_key: op-1" in out


def test_a_retried_add_without_a_seed_asks_for_the_same_start_state(service, cli) -> None:
    rc, out, _ = cli("queue", "add", "--shape", "L", "--idempotency-key", "retry-me", "--json")
    first = json.loads(out)["request"]
    rc, out, _ = cli("queue", "add", "--shape", "L", "--idempotency-key", "retry-me", "--json")
    again = json.loads(out)
    assert rc == 0 and not again["created"] and again["request"]["id"] == first["id"]
    rc, out, _ = cli("queue", "add", "--shape", "L", "--idempotency-key", "other-key", "--json")
    other = json.loads(out)["request"]
    assert other["start_state"] != first["start_state"]  # the key draws the start state
    assert service.queue.counts()["queued"] == 2


def test_refusals_and_usage_errors(service, cli) -> None:
    rc, _, err = cli("queue", "show", "no-such-id")
    assert rc == 1 and err.count("\n") == 1 and "unknown_request" in err
    queued = service.queue.counts()
    for start, why in (('{"shape": "T", "agent": [1, 2]}', "missing ['object']"),
                       ('{"shape": "L", "agent": [1, 2], "object": [256, 256, 0]}',
                        "start_state.shape: expected 'T' (the request's shape), found 'L'")):
        rc, out, err = cli("queue", "add", "--shape", "T", "--start-state", start)
        assert rc == 2 and out == "" and err.count("\n") == 1 and "error: --start-state: " in err and why in err, err
    assert service.queue.counts() == queued  # refused before anything was sent
    with pytest.raises(SystemExit) as info:
        cli("queue", "add", "--shape", "hexagon")
    assert info.value.code == 2


def _watch_while_publishing(service, endpoint: str, namespace: str, count: int, burst: int,
                            as_json: bool = True) -> int | None:
    """``watch --count COUNT [--json]`` in a thread while the service publishes events ``burst`` at a time, until
    the watcher (which subscribes after its first query) has its events; its exit status (None: still running)."""
    result: dict = {}

    def watch() -> None:
        result["rc"] = main(["watch", "--count", str(count), *(["--json"] if as_json else []), "--connect", endpoint,
                             "--namespace", namespace])

    t = threading.Thread(target=watch)
    t.start()
    n = 0
    while t.is_alive() and n < 200 * burst:
        for _ in range(burst):
            service.publish("request.queued", {"request_id": f"r{n}", "source": "test"})
            n += 1
        t.join(0.05)
    t.join(10)
    return result.get("rc")


def test_stats_workers_and_watch(service, cli, endpoint, namespace, capsys) -> None:
    rc, out, _ = cli("stats")
    assert rc == 0 and "requests: queued=0" in out and "episodes: " in out
    assert re.search(r"^disk: +[\d.]+ GiB free of [\d.]+ GiB \(\d+ %\)$", out, re.M), out
    rc, out, _ = cli("workers", "ls", "--json")
    assert rc == 0 and json.loads(out) == {"workers": [], "truncated": False, "total": 0}

    assert _watch_while_publishing(service, endpoint, namespace, count=1, burst=1) == 0
    event = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert event["kind"] == "request.queued" and event["data"]["source"] == "test"


@pytest.mark.parametrize("argv", [["queue", "ls"], ["stats"], ["workers", "ls"], ["watch"],
                                  ["queue", "cancel", "abc"]])
def test_no_service_is_one_line_and_exit_1(argv, namespace, capsys) -> None:
    rc = main([*argv, "--connect", f"tcp/127.0.0.1:{free_port()}", "--namespace", namespace, "--timeout", "0.3"])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "nothing listens at" in err  # (a peer: at once, as a client)
    assert "role" not in err  # no secure profile: an ACL cannot be why


def test_serve_refuses_a_data_directory_that_does_not_exist_unless_told_init(capsys, tmp_path, spawn, endpoint,
                                                                             namespace) -> None:
    missing = tmp_path / "misspelt" / "data"
    argv = ["serve", "--data", str(missing), "--listen", endpoint, "--namespace", namespace, "--planner", "none",
            "--dashboard-port", "-1"]
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and err == (f"activecollect: error: no data directory at {missing}: give the "
                                             "directory a serve, run or collect made, or --init to start a new "
                                             "one there\n")
    assert not (tmp_path / "misspelt").exists()
    # the likeliest slip: the data directory's parent, which exists (it used to start a new, empty catalog there)
    parent = tmp_path / "srv"
    (parent / "data").mkdir(parents=True)
    (parent / "notes.txt").write_text("x")
    assert main([*argv[:2], str(parent), *argv[3:]]) == 2
    assert capsys.readouterr().err.startswith(f"activecollect: error: no catalog in {parent}: give the directory")
    assert sorted(p.name for p in parent.iterdir()) == ["data", "notes.txt"]
    proc = spawn("service", *argv, "--init")
    line = wait_for(lambda: next((ln for ln in proc.log().splitlines() if ln.startswith("serving ")), None)
                    or not proc.alive(), timeout=60, message="serve --init to start")
    assert proc.alive(), proc.log()
    assert line.startswith(f"serving {namespace} listening on {endpoint} (data {missing}, planner none)")
    assert (missing / "catalog.sqlite").is_file()
    assert main(["stats", "--connect", endpoint, "--namespace", namespace, "--timeout", "10", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"]["total"] == 0


def test_serve_says_which_port_its_dashboard_cannot_have(capsys, tmp_path, endpoint, namespace, monkeypatch) -> None:
    """Its dashboard's port is taken: one line with the port and the flag (it was a bare "[Errno 98] Address
    already in use", which reads as the Zenoh endpoint's), exit 1."""
    monkeypatch.setattr("orchestrator.cli.service.on_stop_signals", lambda stop: None)  # keep pytest's handlers
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        rc = main(["serve", "--data", str(tmp_path / "data"), "--init", "--listen", endpoint, "--namespace",
                   namespace, "--planner", "none", "--dashboard-port", str(port)])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1, err
    assert f"cannot serve the dashboard on 127.0.0.1:{port}: Address already in use (--dashboard-port P" in err, err


@pytest.mark.parametrize("schedule", [[], ["--retrain-every", "8"]], ids=["no-retrains", "retrains"])
def test_serve_warns_at_start_when_its_retrains_have_no_eval_split(tmp_path, spawn, endpoint, namespace,
                                                                   schedule) -> None:
    """A new directory has no eval split, which `serve` does not make: scheduled retrains would each fail; said
    once at start (only when it retrains), with the command that makes one."""
    data = tmp_path / "data"
    proc = spawn("service", "serve", "--data", str(data), "--init", "--listen", endpoint, "--namespace", namespace,
                 "--planner", "none", "--dashboard-port", "-1", *schedule)
    # the command's own "serving ..." line, not the service's log line "... INFO serving namespace ...", which
    # comes before the warning
    wait_for(lambda: any(ln.startswith("serving ") for ln in proc.log().splitlines()) or not proc.alive(),
             timeout=60, message="serve to start")
    assert proc.alive(), proc.log()
    warning = f"no eval split is pinned in {data}: every scheduled retrain fails until one is (activecollect " \
              f"eval-split create --data {data}"
    log = proc.log()
    assert (warning in log) == bool(schedule), log  # (written before the "serving" line)


def test_serve_says_how_it_is_reached() -> None:
    from orchestrator.cli.service import where_served
    assert where_served(("tcp/127.0.0.1:7447",), (), None) == "listening on tcp/127.0.0.1:7447"
    assert where_served((), ("tcp/10.0.0.5:7447",), None) == "--connect tcp/10.0.0.5:7447"  # (no link known)
    assert where_served((), ("tcp/10.0.0.5:7447",), None, linked=True) == "connected to tcp/10.0.0.5:7447"
    assert where_served((), (), Path("orchestrator.json5")) == "with Zenoh config orchestrator.json5"
    assert (where_served(("tcp/0.0.0.0:7448",), ("tls/r:7447",), Path("o.json5"))
            == "listening on tcp/0.0.0.0:7448, --connect tls/r:7447, with Zenoh config o.json5")


def test_parse_capabilities() -> None:
    assert parse_capabilities("push:T,box") == (("push",), ("T", "box"))
    assert parse_capabilities("T, L") == ((), ("T", "L"))
    assert parse_capabilities("push") == (("push",), ())
    assert parse_capabilities("") == ((), ())
    with pytest.raises(WorkerError, match="hexagon"):
        parse_capabilities("push:hexagon")


def test_activecollect_worker_once_collects_and_uploads(service, spawn, endpoint, namespace, data_dir) -> None:
    request, _ = service.queue.enqueue(new_request("disk", steps=6))
    proc = spawn("worker-cli", "worker", "--connect", endpoint, "--namespace", namespace, "--id", "cli-w",
                 "--capabilities", "push:disk", "--once", "--size", "16")
    assert proc.wait(120) == 0, proc.log()
    done = service.queue.get(request.id)
    assert (done.status, done.worker_id) == (RequestStatus.DONE, "cli-w")
    ep = Catalog(data_dir).load(done.episode_id)
    assert ep.meta.request_id == request.id and ep.frames.shape == (6, 16, 16, 3)
    wait_for(lambda: "cli-w" not in service.workers(), message="the worker's token goes when it exits")


def test_dispatch_bench_runs_every_phase(tmp_path) -> None:
    result = dispatchbench.run(dispatchbench.BenchConfig(workers=2, seconds=0.3, dispatch_requests=20,
                                                         upload_requests=20, queue_requests=20, data_dir=tmp_path))
    for phase in ("raw_zenoh", "dispatch_lease_fail", "upload_lease_upload"):
        assert result[phase]["cycles"] > 0, phase
    for phase in ("lease_fail", "lease_complete"):
        assert result["queue_in_process"][phase]["cycles"] > 0, phase
    assert set(result["dispatch_lease_fail"]["latency"]) == {"lease", "fail", "cycle"}
    assert "lease_p99_over_raw_p99" in result["goals"]
    assert "lease -> fail" in dispatchbench.format_result(result)


def test_serve_scores_with_one_torch_thread_and_gives_its_retrains_the_other_cores(service) -> None:
    """Both processes busy with more threads than cores slow each other several times over (BENCHMARKS: scoring
    beside a retrain)."""
    from orchestrator.cli import build_parser
    from orchestrator.cli.service import companion_config, planner_factory
    from orchestrator.companions import fitted_retrain_threads
    assert [fitted_retrain_threads(scoring, cores) for scoring, cores in ((1, 2), (1, 16), (4, 2), (0, 16))] == \
        [1, 15, 1, 0]  # (0: the scoring takes torch's default, one thread per core, so the retrain does too)
    args = build_parser().parse_args(["serve"])
    assert args.scoring_threads == 1 and args.retrain_threads is None
    cfg = companion_config(args)
    assert (cfg.scoring_threads, cfg.retrain_threads) == (1, fitted_retrain_threads(1))
    assert cfg.schedule().threads == cfg.retrain_threads
    cfg = companion_config(build_parser().parse_args(["serve", "--scoring-threads", "0", "--retrain-threads", "3"]))
    assert (cfg.scoring_threads, cfg.retrain_threads) == (0, 3)
    assert companion_config(build_parser().parse_args(["serve", "--scoring-threads", "0"])).retrain_threads == 0
    assert planner_factory("active", 20, 0, 3)(service.context).scorer.threads == 3
    assert planner_factory("active", 20, 0)(service.context).scorer.threads == 0  # the library leaves torch alone


def test_serve_takes_a_retrain_timeout_for_its_jobs() -> None:
    """A job trains on every window unless told otherwise: 30 minutes, fixed, was past at ~400 episodes on 2 cores,
    and every scheduled retrain of a growing catalog then failed (a helper's measurement)."""
    from orchestrator.cli import build_parser
    from orchestrator.cli.service import companion_config
    assert companion_config(build_parser().parse_args(["serve"])).schedule().timeout_s == 4 * 3600
    args = build_parser().parse_args(["serve", "--retrain-timeout", "90"])
    assert companion_config(args).schedule().timeout_s == 90


@pytest.mark.parametrize("failing", ["seed", "scheduler"])
def test_serve_reports_a_storage_error_at_start_in_one_line_and_stops_what_it_started(
        failing, capsys, monkeypatch, data_dir, endpoint, port, namespace) -> None:
    """A full disk under ``--seed-requests``, a catalog the retrain scheduler cannot count: exit 1, one line,
    and nothing left serving (the Zenoh listener is closed)."""
    from tests.orchestrator.test_service_storage import port_free, refuse_inserts
    monkeypatch.setattr("orchestrator.cli.service.on_stop_signals", lambda stop: None)  # keep pytest's handlers
    argv = ["serve", "--data", str(data_dir), "--init", "--listen", endpoint, "--namespace", namespace,
            "--dashboard-port", "-1"]
    if failing == "seed":  # a real refusal, by SQLite
        refuse_inserts(Catalog(data_dir).db_path)
        argv += ["--planner", "uniform", "--seed-requests", "2", "--min-queued", "0"]
    else:
        def unreadable(self, *args, **kw) -> int:
            raise CatalogUnavailableError(f"cannot read the catalog {self.db_path}: disk I/O error")

        monkeypatch.setattr(Catalog, "count", unreadable)
        argv += ["--planner", "none", "--retrain-every", "5"]
    rc = main(argv)
    err = capsys.readouterr().err
    wait_for(lambda: port_free(port), message="the service's Zenoh listener to close")
    assert rc == 1 and err.count("\n") == 1 and err.startswith("activecollect serve: "), err
    assert ("no new requests here" if failing == "seed" else "disk I/O error") in err


def test_watch_count_prints_exactly_that_many_events_of_a_burst(service, endpoint, namespace, capsys) -> None:
    """Events that arrive together (a worker's lease, done and stored in one millisecond): ``--count N`` prints
    N of them, not the ones its subscriber was handed while the command was ending."""
    assert _watch_while_publishing(service, endpoint, namespace, count=3, burst=20) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 3 and all(json.loads(line)["kind"] == "request.queued" for line in lines), lines


def test_text_watch_count_prints_that_many_lines_on_stdout(service, endpoint, namespace, capsys) -> None:
    """`watch --count N | wc -l` counted one more: the "watching" line went to stdout, before the events."""
    assert _watch_while_publishing(service, endpoint, namespace, count=2, burst=5, as_json=False) == 0
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    assert len(lines) == 2 and all("request.queued" in line for line in lines), lines
    assert err.startswith("# watching "), err


def test_watch_into_a_closed_pipe_ends_quietly(service, endpoint, namespace) -> None:
    """`watch | head -1`: once the reader is gone, watch ends as any command does on a closed pipe (128 + SIGPIPE,
    no traceback), instead of waiting on for ever while Zenoh's thread logs each failed print."""
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator", "watch", "--connect", endpoint, "--namespace",
                             namespace], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
    try:
        assert proc.stderr.readline().startswith(b"# watching ")
        proc.stdout.close()  # (head has its line)
        n = 0
        while proc.poll() is None and n < 400:  # events until the watcher, subscribed, fails to print one
            service.publish("request.queued", {"request_id": f"r{n}", "source": "test"})
            n += 1
            try:
                proc.wait(0.05)
            except subprocess.TimeoutExpired:
                pass
        ended = proc.poll() is not None or _ended_within(proc, 10)
        if not ended:
            proc.kill()
        err = proc.communicate()[1].decode()
        assert ended, f"watch still running after {n} events into a closed pipe: {err[-2000:]}"
        assert proc.returncode == 128 + signal.SIGPIPE and "Traceback" not in err and "callback" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _ended_within(proc: subprocess.Popen, seconds: float) -> bool:
    try:
        proc.wait(seconds)
        return True
    except subprocess.TimeoutExpired:
        return False


def test_dispatch_bench_refuses_a_data_directory_a_run_left(tmp_path, capsys) -> None:
    """A second run on the same --data leased the first run's leftover requests, for which it had no episode: its
    upload clients died (KeyError), and it printed 0 uploads/s and exited 0."""
    dispatchbench.run(dispatchbench.BenchConfig(workers=1, seconds=0.2, dispatch_requests=5, upload_requests=5,
                                                queue_requests=5, data_dir=tmp_path))
    rc, out, err = run_cli(capsys, "bench", "dispatch", "--seconds", "0.2", "--data", str(tmp_path))
    assert rc == 2 and out == ""
    assert err.splitlines() == [f"activecollect: error: --data {tmp_path} is not an empty directory; "
                                "give a new or empty one"]
