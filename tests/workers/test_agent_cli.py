"""The worker's command line, as ``activecollect worker`` and as ``python -m workers.agent``: a bad flag
exits 2 in one line that names the program run and the flag typed; the help says what the code does."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import types

import pytest

from orchestrator.cli import build_parser
from orchestrator.protocol import MAX_CAPABILITIES
import workers.agent
from tests.conftest import REPO, free_port
from workers import cli as worker_cli
from workers.agent import Worker, WorkerConfig, WorkerError
from workers.env import CONTROL_HZ

CLI, MODULE = "activecollect worker", "python -m workers.agent"


def _stops(capsys, prog: str, *argv: str) -> tuple[int, str]:
    """(exit status, stderr) of PROG ARGV, which must stop before a worker starts: one that started would
    wait for a service for ever (nobody listens on its --connect)."""
    argv = (*argv, "--connect", f"tcp/127.0.0.1:{free_port()}")
    try:
        if prog == CLI:
            args = build_parser().parse_args(["worker", *argv])
        else:
            args = worker_cli.build_parser().parse_args(argv)
    except SystemExit as exc:
        return exc.code, capsys.readouterr().err
    with pytest.raises(WorkerError):
        worker_cli.config_from_args(args)
    return worker_cli.run_from_args(args), capsys.readouterr().err


@pytest.mark.parametrize("prog", [CLI, MODULE])
@pytest.mark.parametrize("argv, words", [
    (["--size", "30"], "argument --size: expected a multiple of 8 from 16 to 1024 (what a model trains on), found 30"),
    (["--realtime", "inf"], "argument --realtime: expected a number from 0 (flat out) to 1000, found 'inf'"),
    (["--realtime", "1e300"], "argument --realtime: expected a number from 0 (flat out) to 1000, found '1e300'"),
    (["--realtime", "nan"], "argument --realtime: expected a number from 0 (flat out) to 1000, found 'nan'"),
    (["--realtime", "-1"], "argument --realtime: expected a number from 0 (flat out) to 1000, found '-1'"),
    (["--realtime", "fast"], "argument --realtime: expected a number from 0 (flat out) to 1000, found 'fast'"),
    (["--max-episodes", "-1"], "argument --max-episodes: expected a positive integer, found -1"),
    (["--max-episodes", "0"], "argument --max-episodes: expected a positive integer, found 0"),
    (["--max-episodes", "1e9"], "argument --max-episodes: expected a positive integer, found '1e9'"),
    (["--id", "a/b"], "--id: expected 1-128 characters of [A-Za-z0-9_.-], found 'a/b'"),
    (["--capabilities", "push:hexagon"], "--capabilities: expected TASK:SHAPE,... with tasks in ('push',) and "
                                         "shapes in ('T', 'box', 'L', 'disk'), found hexagon"),
    (["--capabilities", ":"], "--capabilities: expected a task before ':' (tasks in ('push',)), found ':'"),
    (["--capabilities", ":T,box"], "--capabilities: expected a task before ':' (tasks in ('push',)), found ':T,box'"),
    (["--capabilities", " , "], "--capabilities: expected TASK:SHAPE,... with tasks in ('push',) and shapes in "
                                "('T', 'box', 'L', 'disk'), found no task or shape in ','"),
    (["--capabilities", ",".join(["T"] * (MAX_CAPABILITIES + 1))],
     f"--capabilities: expected a list of at most {MAX_CAPABILITIES} strings"),
    # empty (an unset shell variable): not the default by stealth
    (["--id", ""], "--id: expected a value, found '' (leave the flag out for <host>-<pid>)"),
    (["--capabilities", " "], "--capabilities: expected a value, found ' ' (leave the flag out for anything)"),
    (["--namespace", "a b"], "--namespace: expected chunks of [A-Za-z0-9_-] joined by '/', found 'a b'"),
])
def test_a_bad_flag_exits_2_in_one_line_naming_the_program_and_the_flag(capsys, prog, argv, words) -> None:
    rc, err = _stops(capsys, prog, *argv)
    assert rc == 2 and err.startswith(f"{prog}: error: {words}") and err.count("\n") == 1, err


@pytest.mark.parametrize("argv, words", [
    (["--size", "30"], "argument --size: expected a multiple of 8 from 16 to 1024"),
    (["--id", "a/b"], "--id: expected 1-128 characters"),  # found after parsing, by the config
])
def test_python_m_workers_agent_says_so_in_one_line(argv, words) -> None:
    """The real program: no usage block, and its own name, not ``activecollect worker``."""
    proc = subprocess.run([sys.executable, "-m", "workers.agent", *argv, "--connect", f"tcp/127.0.0.1:{free_port()}"],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert proc.stderr.startswith(f"{MODULE}: error: {words}") and proc.stderr.count("\n") == 1, proc.stderr


def test_the_flags_take_their_whole_range() -> None:
    args = worker_cli.build_parser().parse_args(["--realtime", "0", "--max-episodes", "1", "--id", "w-1.a_b",
                                            "--capabilities", "push:T,box", "--namespace", "lab/a-1"])
    config = worker_cli.config_from_args(args)
    assert (config.realtime, config.max_episodes, config.worker_id) == (0.0, 1, "w-1.a_b")
    assert (config.tasks, config.shapes, config.namespace) == (("push",), ("T", "box"), "lab/a-1")
    assert worker_cli.build_parser().parse_args(["--realtime", "1000"]).realtime == 1000.0
    assert worker_cli.build_parser().parse_args([]).max_episodes is None  # until stopped


@pytest.mark.parametrize("field, value, words", [
    ("realtime", math.inf, "realtime: expected a number from 0 (flat out) to 1000, found inf"),
    ("realtime", -1.0, "realtime: expected a number from 0 (flat out) to 1000, found -1.0"),
    ("realtime", math.nan, "realtime: expected a number from 0 (flat out) to 1000, found nan"),
    ("idle_poll_s", math.inf, "idle_poll_s: expected seconds in (0, 86400], found inf"),
    ("timeout_s", 0.0, "timeout_s: expected seconds in (0, 86400], found 0.0"),
    ("max_backoff_s", math.nan, "max_backoff_s: expected seconds in (0, 86400], found nan"),
    ("max_episodes", 0, "max_episodes: expected a positive integer (None: no limit), found 0"),
])
def test_the_config_refuses_a_wait_that_would_overflow_or_never_end(field, value, words) -> None:
    with pytest.raises(WorkerError) as exc:
        WorkerConfig(**{field: value})
    assert str(exc.value) == words
    assert WorkerConfig(realtime=0.0).realtime == 0.0  # flat out


def _help(flag: str) -> str:
    action = next(a for a in worker_cli.build_parser()._actions if flag in a.option_strings)
    return " ".join(action.help.split())


def test_the_help_says_what_the_flags_do() -> None:
    assert "at least X * steps / 10 seconds" in _help("--realtime") and "2 = half speed" in _help("--realtime")
    assert "exit at once when the service has no work" in _help("--once")
    assert _help("--timeout").startswith("seconds")
    assert "run until stopped" in _help("--max-episodes")


def test_realtime_x_makes_an_episode_last_x_times_its_steps_at_the_control_rate(monkeypatch) -> None:
    """What ``--realtime``'s help promises: 2 is half a real robot's speed (0.2 s a step at 10 Hz). On a clock of
    the test's, which moves only while the worker waits (no wall-clock figure)."""
    now = [0.0]

    class Abort(threading.Event):  # the worker's give-back event: waiting on it moves the clock on
        def wait(self, timeout: float | None = None) -> bool:
            if not self.is_set() and timeout is not None:
                now[0] += timeout
            return self.is_set()

    monkeypatch.setattr(workers.agent, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    worker = Worker(WorkerConfig(realtime=2.0))
    worker._abort = Abort()
    assert worker._pace(0.0, frames=2)
    assert now[0] == pytest.approx(2.0 * 2 / CONTROL_HZ)  # waited exactly that long, no less
    worker._abort.set()  # given back: no wait
    assert not worker._pace(now[0], frames=1000) and now[0] == pytest.approx(2.0 * 2 / CONTROL_HZ)
