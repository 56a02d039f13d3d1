"""Shared test fixtures: free ports, data dirs, real service/worker subprocesses, wait_for.

Import the plain helpers with ``from tests.conftest import wait_for, free_port``;
the fixtures are found by pytest on their own.
"""

from __future__ import annotations

import errno
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

import pytest

from orchestrator.cli import main

REPO = Path(__file__).resolve().parents[1]
T = TypeVar("T")


@pytest.fixture(autouse=True, scope="session")
def sigint_as_in_a_terminal() -> Iterator[None]:
    """Children start with SIGINT's default disposition even when the suite itself was started in the
    background of a script, which starts it with SIGINT ignored (and an ignored signal stays ignored across
    exec, so `run` would ignore the test's Ctrl-C while its workers, which catch it, stopped). The tests
    that send SIGINT stand for a terminal's Ctrl-C."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def disposition(pid: int, sig: int) -> str:
    """How a process takes ``sig``: ``ignored``, ``caught`` (a handler) or ``default``, as Linux reports it."""
    fields = dict(line.split(":\t") for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                  if line.startswith(("SigIgn", "SigCgt")))
    bit = 1 << (sig - 1)
    return "ignored" if int(fields["SigIgn"], 16) & bit else "caught" if int(fields["SigCgt"], 16) & bit else "default"


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def children(pid: int) -> dict[int, str]:
    """The live child processes of ``pid``: {pid: command line}."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # (after the command name, which may hold spaces)
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:  # gone meanwhile
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found[int(stat.parent.name)] = cmdline.replace(b"\0", b" ").decode(errors="replace")
    return found


@contextmanager
def ignoring_sigint() -> Iterator[None]:
    """Children started in this block inherit SIGINT ignored across exec, as a script's background jobs do."""
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def wait_for(condition: Callable[[], T], timeout: float = 10.0, message: str = "condition",
             interval: float = 0.02) -> T:
    """Poll ``condition`` until it returns something truthy; return that value.

    Raises ``AssertionError`` naming ``message`` (and the last value seen) when
    ``timeout`` seconds pass first.
    """
    deadline = time.monotonic() + timeout
    last: T | None = None
    while time.monotonic() < deadline:
        last = condition()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {message}; last value: {last!r}")


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def endpoint(port: int) -> str:
    """A loopback Zenoh endpoint with a free port, for one test's service to listen on."""
    return f"tcp/127.0.0.1:{port}"


@pytest.fixture
def namespace() -> str:
    """A namespace unique to the test, so nothing leaks between deployments."""
    return f"t{uuid.uuid4().hex[:10]}"


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    d = tmp_path / "data"
    d.mkdir()
    return d


class Proc:
    """A subprocess started by :func:`spawn` with its combined output in a log file."""

    def __init__(self, name: str, args: Sequence[str], log_path: Path, env: dict[str, str]) -> None:
        self.name = name
        self.args = list(args)
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.popen = subprocess.Popen(self.args, stdout=self._log, stderr=subprocess.STDOUT,
                                      cwd=REPO, env=env, start_new_session=True)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            os.kill(self.popen.pid, sig)

    def wait(self, timeout: float = 20.0) -> int:
        """Wait for exit; return the exit code (raises subprocess.TimeoutExpired)."""
        return self.popen.wait(timeout)

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL if it does not exit in ``timeout``; close the log."""
        if self.alive():
            self.signal(signal.SIGCONT)  # a stopped process cannot act on SIGTERM
            self.signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.signal(signal.SIGKILL)
                self.popen.wait(timeout)
        self._log.close()
        return self.popen.returncode


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., Proc]]:
    """Factory ``spawn(name, *cli_args, module="orchestrator")`` running ``python -m MODULE *cli_args``.

    Every process is stopped at teardown; a failing test prints their logs.
    """
    procs: list[Proc] = []
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))

    def _spawn(name: str, *cli_args: str, module: str = "orchestrator") -> Proc:
        log_path = tmp_path / f"{name}.{len(procs)}.log"
        proc = Proc(name, [sys.executable, "-m", module, *cli_args], log_path, env)
        procs.append(proc)
        return proc

    yield _spawn
    workers_first = sorted(reversed(procs), key=lambda p: not p.name.startswith("worker"))
    for proc in workers_first:  # workers before the service they talk to
        proc.stop()
    for proc in procs:
        sys.stdout.write(f"\n----- {proc.name} (pid {proc.pid}, rc {proc.popen.returncode}) -----\n")
        sys.stdout.write(proc.log()[-4000:])


@pytest.fixture
def spawn_service(spawn: Callable[..., Proc], data_dir: Path, endpoint: str,
                  namespace: str) -> Callable[..., Proc]:
    """Factory ``spawn_service(*extra_args)``: ``activecollect serve`` on this test's endpoint and data dir."""

    def _service(*extra: str, name: str = "service") -> Proc:
        return spawn(name, "serve", "--data", str(data_dir), "--init", "--namespace", namespace,
                     "--listen", endpoint, "--planner", "none", "--reap-interval-s", "0.2",
                     "--lost-worker-grace", "0", "--dashboard-port", "-1", *extra)

    return _service


@pytest.fixture
def spawn_worker(spawn: Callable[..., Proc], endpoint: str, namespace: str) -> Callable[..., Proc]:
    """Factory ``spawn_worker(worker_id, *extra_args)``: a worker connected to the test's service.

    Runs ``python -m workers.agent`` (the same flags as ``activecollect worker``, without
    importing the CLI's torch-heavy command groups, so it starts in about a second).
    """

    def _worker(worker_id: str, *extra: str) -> Proc:
        return spawn(f"worker-{worker_id}", "--connect", endpoint, "--namespace", namespace,
                     "--id", worker_id, "--size", "16", *extra, module="workers.agent")

    return _worker


def in_hand(worker: Proc, request_id: str, timeout: float = 30.0) -> None:
    """Wait until ``worker`` holds ``request_id`` (its log says ``leased ID token``): past its drain check, so a
    drain signal from now on finishes this request. (The queue shows the lease a moment earlier, while the grant is
    still on its way to the worker: a signal then gives the request back, "granted after the drain began".)"""
    wait_for(lambda: holds(worker.log(), request_id), timeout=timeout,
             message=f"worker {worker.name} to hold {request_id}")


def holds(worker_log: str, request_id: str) -> bool:
    """Whether a worker's log says it holds ``request_id`` (see ``in_hand``)."""
    return f" leased {request_id} token " in worker_log


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    """``activecollect ARGV`` in this process: (exit status, stdout, stderr); usage errors give 2."""
    try:
        rc = main(list(argv))
    except SystemExit as exc:  # argparse usage errors
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def failing_reads_of(path: Path, monkeypatch, times: int = 1, code: int = errno.EIO) -> list[Path]:
    """The next ``times`` ``read_bytes`` of ``path`` raise ``OSError(code)``, as a flaky disk's would (a read that
    may pass); the list returned records each failed read."""
    real, failed = Path.read_bytes, []

    def read_bytes(self: Path) -> bytes:
        if self == path and len(failed) < times:
            failed.append(self)
            raise OSError(code, os.strerror(code))
        return real(self)
    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    return failed


def failing_prune_claims_of(monkeypatch, fails: Callable[[Path], bool], code: int = errno.EACCES) -> None:
    """A prune's claim of a folder for which ``fails(folder)`` holds (its ``os.rename`` to ``.prune-*``) fails with
    ``OSError(code)``, as on a read-only ``models/``, which root, running the tests here, would not see; every
    other rename is real."""
    failing_renames_of(monkeypatch, fails, code, call="rename")


def failing_renames_of(monkeypatch, fails: Callable[[Path], bool], code: int, call: str = "replace") -> None:
    """``os.replace`` (or ``os.<call>``) of a source for which ``fails(src)`` holds raises ``OSError(code)`` (EXDEV:
    to another file system; ENOSPC: no room for one more directory entry); every other rename is real."""
    real = getattr(os, call)

    def renamed(src, dst, **kw) -> None:
        if fails(Path(src)):
            raise OSError(code, os.strerror(code), str(src), str(dst))
        real(src, dst, **kw)
    monkeypatch.setattr(os, call, renamed)
