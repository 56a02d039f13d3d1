"""Commands that do not train, evaluate or score start without importing torch.

Every check runs a real ``python`` subprocess (a module imported by an earlier test in
this process would hide the import), runs the command through ``orchestrator.cli.main``
and reports afterwards whether ``torch`` (and ``matplotlib``, which only drawing needs)
is in ``sys.modules``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import urllib.request

import pytest

from storage.catalog import Catalog
from tests.conftest import REPO, free_port, wait_for

#: Runs ``activecollect ARGV`` and then writes marker lines saying whether torch / matplotlib were imported.
WRAPPER = """
import sys
from orchestrator.cli import main
try:
    rc = main(sys.argv[1:])
except SystemExit as exc:
    rc = exc.code
sys.stderr.write(f"\\nTORCH_IMPORTED={'torch' in sys.modules}\\n")
sys.stderr.write(f"MATPLOTLIB_IMPORTED={'matplotlib' in sys.modules}\\n")
sys.exit(rc)
"""
ENV = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")


def _imported(stderr: str, module: str) -> bool:
    mark = f"{module.upper()}_IMPORTED="
    marks = [line for line in stderr.splitlines() if line.startswith(mark)]
    assert marks, f"the wrapper wrote no {mark} line; stderr:\n{stderr[-2000:]}"
    return marks[-1] == f"{mark}True"


def _imported_torch(stderr: str) -> bool:
    return _imported(stderr, "torch")


def _cli(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", WRAPPER, *argv], capture_output=True, text=True,
                          cwd=REPO, env=ENV, timeout=timeout)


def test_torch_free_modules_do_not_import_torch():
    """The parser, the config modules and everything ``serve`` starts with."""
    code = ("import sys, json\n"
            "import orchestrator.cli, orchestrator.champion, orchestrator.companions, orchestrator.loopconfig, "
            "orchestrator.scheduler, uncertainty.config\n"
            "orchestrator.cli.build_parser()\n"
            "print(json.dumps(sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=ENV,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == []


def test_help_imports_neither_torch_nor_matplotlib():
    proc = _cli("--help")
    assert proc.returncode == 0, proc.stderr
    assert "COMMAND" in proc.stdout
    assert not _imported_torch(proc.stderr)
    assert not _imported(proc.stderr, "matplotlib")  # only drawing a figure needs it (0.15-0.4 s to import)


@pytest.mark.parametrize("argv", [
    ["secure", "--help"],
    ["bench", "loop", "--help"],
    ["retrain", "--help"],
    ["queue", "ls", "--connect", "tcp/127.0.0.1:{port}", "--timeout", "0.5"],
    ["workers", "ls", "--connect", "tcp/127.0.0.1:{port}", "--timeout", "0.5"],
], ids=lambda argv: "-".join(a for a in argv[:2] if not a.startswith("-")))
def test_command_does_not_import_torch(argv):
    proc = _cli(*(a.format(port=free_port()) for a in argv))
    assert proc.returncode in (0, 1), proc.stderr  # 1: no service answered, said in one line
    assert not _imported_torch(proc.stderr), proc.stderr[-2000:]


def test_catalog_and_registry_commands_do_not_import_torch(tmp_path):
    data = str(tmp_path / "data")
    for argv in (["collect", "--episodes", "1", "--size", "16", "--steps", "5", "--data", data],
                 ["episodes", "ls", "--data", data], ["episodes", "verify", "--data", data],
                 ["models", "ls", "--data", data]):
        proc = _cli(*argv)
        assert proc.returncode == 0, proc.stderr
        assert not _imported_torch(proc.stderr), f"{argv}: {proc.stderr[-2000:]}"


def test_serve_without_a_champion_does_not_import_torch(tmp_path):
    """``serve`` with the active planner and the dashboard: torch waits for a champion to load."""
    log_path = tmp_path / "serve.log"
    argv = ["serve", "--init", "--data", str(tmp_path / "data"), "--listen", f"tcp/127.0.0.1:{free_port()}",
            "--namespace", "startup", "--planner", "active", "--dashboard-port", "0"]
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-c", WRAPPER, *argv], stdout=log, stderr=subprocess.STDOUT,
                                cwd=REPO, env=ENV, start_new_session=True)
    try:
        line = wait_for(lambda: next((ln for ln in log_path.read_text().splitlines()
                                      if ln.startswith("dashboard at ")), None) or proc.poll() is not None,
                        timeout=60, message="serve to start its dashboard")
        assert proc.poll() is None, log_path.read_text()
        url = line.split()[-1].rstrip("/")
        with urllib.request.urlopen(f"{url}/frames.png", timeout=30) as reply:  # asks the champion scorer
            assert reply.status == 200
        proc.terminate()
        assert proc.wait(timeout=30) == 0, log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not _imported_torch(log_path.read_text()), log_path.read_text()[-2000:]


def test_training_commands_still_load_torch(tmp_path):
    """The other side: ``train`` imports the models when it runs (here: to refuse an empty catalog)."""
    data = tmp_path / "data"
    Catalog(data)  # empty (without one, train refuses before loading anything: exit 2)
    proc = _cli("train", "--data", str(data), "--epochs", "1")
    assert proc.returncode == 1, proc.stderr
    assert "training failed" in proc.stderr
    assert _imported_torch(proc.stderr)



@pytest.mark.parametrize("argv, rc, words", [
    (("train", "--min-improvement", "2"), 2, "argument --min-improvement"),
    (("eval",), 1, "no champion model yet"),
    (("score", "nosuchepisode"), 2, "no episode 'nosuchepisode'"),
])
def test_model_commands_refuse_bad_requests_before_loading_torch(tmp_path, argv, rc, words):
    """A mistake in what was asked is told without paying for the torch import."""
    data = tmp_path / "data"
    Catalog(data)  # empty
    proc = _cli(*argv, "--data", str(data))
    assert proc.returncode == rc, proc.stderr
    assert words in proc.stderr
    assert not _imported_torch(proc.stderr), proc.stderr


def test_a_reader_that_goes_away_ends_the_command_quietly(tmp_path):
    """`activecollect models ls | head -0`: no BrokenPipeError traceback, the shell's SIGPIPE status."""
    Catalog(tmp_path)  # empty
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the command writes a byte
    try:
        proc = subprocess.run([sys.executable, "-m", "orchestrator", "models", "ls", "--data", str(tmp_path)],
                              stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=REPO, env=ENV, timeout=120)
    finally:
        os.close(write_end)
    assert proc.returncode == 141 and "Traceback" not in proc.stderr, proc.stderr
