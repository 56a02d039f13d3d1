"""A command that runs out of memory says so in one line (exit 1), as a full disk does, not with a traceback."""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys

import pytest
import torch

from orchestrator import cli
from tests.conftest import REPO


@pytest.mark.skipif(torch.version.cuda is not None, reason="a CUDA build maps more than the limit when it loads")
def test_an_allocation_torch_cannot_make_is_one_line_and_exit_1():
    def limit() -> None:  # (a child's address space: the allocation fails here whatever the machine's memory)
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    done = subprocess.run([sys.executable, "-m", "orchestrator", "bench", "score", "--batch", "100000000",
                           "--members", "2", "--seconds", "1", "--device", "cpu"],
                          preexec_fn=limit, capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("activecollect: out of memory: ") and "a smaller --batch" in done.stderr


@pytest.mark.parametrize("error,said", [
    (MemoryError(), "out of memory: an allocation failed"),
    (RuntimeError("CUDA out of memory. Tried to allocate 20.00 GiB\nmore"), "out of memory: CUDA out of memory."),
])
def test_numpys_and_cudas_out_of_memory_are_one_line(monkeypatch, capsys, error, said):
    if "CUDA" in str(error):
        error = type("OutOfMemoryError", (RuntimeError,), {})(str(error))  # torch.OutOfMemoryError's name
    monkeypatch.setattr(cli, "build_parser", lambda: _raising(error))
    assert cli.main(["x"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and said in err


def test_any_other_runtime_error_keeps_its_traceback(monkeypatch):
    monkeypatch.setattr(cli, "build_parser", lambda: _raising(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["x"])


def _raising(error: BaseException):
    """A parser whose one command raises ``error``."""

    def func(args):
        raise error

    parser = argparse.ArgumentParser()
    parser.add_argument("cmd")
    parser.set_defaults(func=func)
    return parser
