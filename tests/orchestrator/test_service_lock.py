"""One service per data directory (``storage.servicelock``): a second ``serve`` or ``run`` on a directory a live
service holds is refused in one line naming the holder and changes nothing there; the lock goes with its holder
(``stop()``, or the kernel at a SIGKILL, whatever children it left running)."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.cli import main
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig, ServiceError
from storage.catalog import Catalog
from storage.queue import RequestQueue
from storage.servicelock import LOCK_NAME, read_holder
from tests.conftest import REPO, children as child_processes, free_port, wait_for
from tests.orchestrator.test_service import new_request

#: A child that outlives the service that started it: it ignores the SIGTERM ``die_with_parent`` sends.
OUTLIVES = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(300)  # outlives"

#: A service that starts a retrain job (through the real scheduler) and a bare child (``close_fds=False``), both
#: of the kind in OUTLIVES. argv: DATA ENDPOINT NAMESPACE
HOLDER = f"""
import subprocess, sys, threading
from pathlib import Path
from orchestrator.retrainjob import ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
data, endpoint, namespace = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
child = [sys.executable, "-c", {OUTLIVES!r}]
Service(ServiceConfig(data_dir=data, namespace=namespace, listen=(endpoint,))).start()
scheduler = RetrainScheduler(ScheduleConfig(poll_s=0.05), data, lambda: 0, command=lambda data, extra: child)
scheduler.start()
scheduler.request("test")
subprocess.Popen(child, close_fds=False)
print("serving", flush=True)
threading.Event().wait()
"""


def serving(proc) -> str:
    """Waits for ``serve``'s "serving" line; the log so far."""
    def log_once_up() -> str:
        log = proc.log()
        return log if "serving " in log or not proc.alive() else ""

    return wait_for(log_once_up, timeout=60, message=f"{proc.name} to serve")


def snapshot(data: Path) -> tuple:
    """What a second service must not change: every request as it stands, the catalog's rows, the files."""
    queue = RequestQueue(data / "catalog.sqlite")
    try:
        requests = sorted((r.id, r.status.value, r.token, r.attempts, r.lease_expires) for r in queue.list())
    finally:
        queue.close()
    episodes = [(r.episode_id, r.path) for r in Catalog(data).list()]
    return requests, episodes, sorted(str(p.relative_to(data)) for p in data.rglob("*"))


def serve_argv(data: Path, endpoint: str, namespace: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "orchestrator", "serve", "--data", str(data), "--namespace", namespace,
            "--listen", endpoint, *extra]


def stats(endpoint: str, namespace: str, capsys) -> dict:
    assert main(["stats", "--connect", endpoint, "--namespace", namespace, "--timeout", "10", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def held_state(data: Path, endpoint: str, namespace: str, spawn_service) -> tuple:
    """A ``serve`` on ``data`` with something each start-up step of another service would change: a live lease
    (its term extended), an unindexed episode file (moved to orphans/), a queue below a floor (topped up)."""
    first = spawn_service("--lease-s", "600")
    assert "serving " in serving(first), first.log()
    queue = RequestQueue(data / "catalog.sqlite")
    queue.enqueue(new_request())
    queue.lease("w1", lease_s=100.0)
    queue.close()
    stray = data / "episodes" / "2026-01-01" / "0123456789abcdef0123456789abcdef.mcap"
    stray.parent.mkdir(parents=True)
    stray.write_bytes(b"renamed into place, then a crash before the commit")
    return first, stray


def test_a_second_serve_is_refused_in_one_line_naming_the_first_and_changes_nothing(
        spawn_service, data_dir, endpoint, namespace, capsys) -> None:
    first, stray = held_state(data_dir, endpoint, namespace, spawn_service)
    before = snapshot(data_dir)

    second = subprocess.run(serve_argv(data_dir, f"tcp/127.0.0.1:{free_port()}", namespace, "--planner", "uniform",
                                       "--min-queued", "3", "--lease-s", "600", "--dashboard-port", "0"),
                            capture_output=True, text=True, cwd=REPO, timeout=60)

    lock = data_dir / LOCK_NAME
    assert second.returncode == 1 and second.stdout == "", second
    assert second.stderr.count("\n") == 1, second.stderr  # no traceback, no log line, no dashboard
    assert second.stderr.startswith(f"activecollect serve: another service holds {lock} (pid {first.pid}, "
                                    f"started "), second.stderr
    assert f"listening on {endpoint}, namespace {namespace}): one service per data directory" in second.stderr
    assert snapshot(data_dir) == before and stray.is_file()
    assert read_holder(lock)["pid"] == first.pid
    assert first.alive() and stats(endpoint, namespace, capsys)["requests"]["leased"] == 1  # the first serves on


def test_run_on_a_directory_a_serve_holds_is_refused_in_one_line_and_changes_nothing(
        spawn_service, data_dir, endpoint, namespace, capsys) -> None:
    """`run` starts a service in-process: it is refused before its set-up writes (no eval split, no worker, no
    report)."""
    first, stray = held_state(data_dir, endpoint, namespace, spawn_service)
    before = snapshot(data_dir)

    run = subprocess.run([sys.executable, "-m", "orchestrator", "run", "--data", str(data_dir), "--budget", "2",
                          "--round", "2", "--workers", "1", "--image-size", "16", "--steps", "8",
                          "--eval-episodes", "1", "--dashboard-port", "-1", "--no-progress"],
                         capture_output=True, text=True, cwd=REPO, timeout=90)

    assert run.returncode == 1 and run.stdout == "", run
    assert run.stderr.count("\n") == 1, run.stderr
    assert run.stderr.startswith(f"activecollect: another service holds {data_dir / LOCK_NAME} (pid {first.pid}, "
                                 f"started "), run.stderr
    assert snapshot(data_dir) == before and stray.is_file()
    assert first.alive() and stats(endpoint, namespace, capsys)["requests"]["leased"] == 1


def test_a_second_service_in_one_process_is_refused_and_one_after_stop_starts(data_dir, namespace) -> None:
    def service() -> Service:
        return Service(ServiceConfig(data_dir=data_dir, namespace=namespace,
                                     listen=(f"tcp/127.0.0.1:{free_port()}",)))

    first = service()
    first.start()
    try:
        second = service()
        try:
            with pytest.raises(ServiceError, match=rf"^another service holds .*{LOCK_NAME} \(pid {os.getpid()}, "):
                second.start()
        finally:
            second.stop()  # (a no-op after a refused start; one that was not refused must not outlive the test)
        assert second.session is None and second.queue is None  # refused before it opened anything
        request, _ = first.queue.enqueue(new_request())  # the first serves on
        assert first.queue.get(request.id) == request
        lock_fds = [int(fd) for fd in os.listdir("/proc/self/fd")
                    if os.path.realpath(f"/proc/self/fd/{fd}") == str((data_dir / LOCK_NAME).resolve())]
        assert len(lock_fds) == 1  # the refused start closed its own
        assert fcntl.fcntl(lock_fds[0], fcntl.F_GETFD) & fcntl.FD_CLOEXEC  # no exec'd child keeps it
    finally:
        first.stop()
    again = service()
    again.start()  # stop() let the directory go
    again.stop()


def test_the_holders_text_claims_no_connection_to_its_connect_endpoints(data_dir, namespace) -> None:
    """It said "connected to EP", written before the session opened, of an endpoint nothing listened on (a peer's
    session opens without a link and keeps dialling)."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    first = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, connect=(dead,)))
    first.start()
    try:
        assert read_holder(data_dir / LOCK_NAME)["where"] == f"--connect {dead}"
        second = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, connect=(dead,)))
        with pytest.raises(ServiceError) as refusal:
            second.start()
        assert f"(pid {os.getpid()}, " in str(refusal.value) and f", --connect {dead}, namespace " in str(refusal.value)
        assert "connected" not in str(refusal.value)
    finally:
        first.stop()


def _children(pid: int) -> list[int]:
    """The OUTLIVES processes whose parent is ``pid``."""
    return [child for child, cmdline in child_processes(pid).items() if "# outlives" in cmdline]


def test_a_service_sigkilled_with_children_alive_leaves_the_directory_free(data_dir, endpoint, namespace,
                                                                          tmp_path) -> None:
    """The kernel drops the lock with its holder: a retrain job (started by the real scheduler) and a bare child
    that outlive the SIGKILLed service do not keep it, and a service started right after starts."""
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    with open(tmp_path / "holder.log", "wb") as log:
        holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(data_dir), endpoint, namespace], cwd=REPO,
                                  env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: b"serving" in (tmp_path / "holder.log").read_bytes() or holder.poll() is not None,
                 timeout=60, message="the holder to serve")
        children = wait_for(lambda: len(c := _children(holder.pid)) == 2 and c, timeout=30,
                            message="its retrain job and its bare child")
        intruder = Service(ServiceConfig(data_dir=data_dir, namespace=namespace,
                                         listen=(f"tcp/127.0.0.1:{free_port()}",)))
        try:
            with pytest.raises(ServiceError, match=rf"another service holds .* \(pid {holder.pid}, "):
                intruder.start()
        finally:
            intruder.stop()
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait(10)
        for child in children:
            os.kill(child, 0)  # alive: it outlived the service
        restarted = Service(ServiceConfig(data_dir=data_dir, namespace=namespace, listen=(endpoint,)))
        restarted.start()
        restarted.stop()
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(holder.pid, signal.SIGKILL)  # the holder and its children: its own session, its group
        holder.wait()
