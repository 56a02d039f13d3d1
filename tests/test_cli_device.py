"""Every ``--device`` is checked when the arguments are parsed: a device this machine cannot use
(cuda without CUDA) or a name torch's devices are not called exits 2 in one line naming the flag,
before a command loads a model, opens a catalog or trains; ``auto`` and ``cpu`` need no torch.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from orchestrator.cli import build_parser
from tests.conftest import REPO, run_cli
from uncertainty.benchmark import run_score_bench
from uncertainty.errors import ConfigError

NO_CUDA = not torch.cuda.is_available()

#: Every command with a ``--device`` of its own, or of the retrain jobs it runs (``--retrain-args``).
COMMANDS = {
    "train": ["train", "--data", "{data}", "--device", "{device}"],
    "eval": ["eval", "--data", "{data}", "--device", "{device}"],
    "score": ["score", "e000001", "--data", "{data}", "--device", "{device}"],
    "retrain": ["retrain", "--data", "{data}", "--device", "{device}"],
    "bench score": ["bench", "score", "--size", "16", "--members", "2", "--seconds", "0.1", "--device", "{device}"],
    "bench loop": ["bench", "loop", "--out", "{data}", "--device", "{device}"],
    "run": ["run", "--data", "{data}", "--retrain-args", "--members 2 --device '{device}'"],
    "serve": ["serve", "--data", "{data}", "--retrain-args", "--device '{device}'"],
}


def _argv(name: str, device: str, data) -> list[str]:
    return [a.format(data=data, device=device) for a in COMMANDS[name]]


def _refused(capsys, argv: list[str]) -> str:
    """The one line a refused command wrote (asserting exit 2 and nothing else on stdout or stderr)."""
    rc, out, err = run_cli(capsys, *argv)
    lines = err.strip().splitlines()
    assert rc == 2 and not out and len(lines) == 1, (rc, out, err)
    return lines[0]


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA: --device cuda is valid here")
@pytest.mark.parametrize("name", COMMANDS)
def test_cuda_without_cuda_is_a_usage_error_naming_the_flag(capsys, tmp_path, name):
    line = _refused(capsys, _argv(name, "cuda", tmp_path / "data"))
    assert "--device" in line and "CUDA is not available on this machine" in line, line
    assert torch.__version__ in line and "use --device cpu or leave it out" in line, line
    assert not (tmp_path / "data").exists()  # refused before anything was made


@pytest.mark.parametrize("device", ["gpu", "CUDA", "", "cuda:0", "cuda:99", "cpu:0", "mps"])
@pytest.mark.parametrize("name", COMMANDS)
def test_a_device_name_of_no_torch_device_is_a_usage_error(capsys, tmp_path, name, device):
    line = _refused(capsys, _argv(name, device, tmp_path / "data"))
    assert "--device" in line and "expected one of auto, cpu, cuda" in line and repr(device) in line, line
    assert ("CUDA_VISIBLE_DEVICES" in line) == device.startswith("cuda:"), line


@pytest.mark.skipif(NO_CUDA, reason="no CUDA here")
@pytest.mark.parametrize("name", ["train", "eval", "score", "retrain", "bench score", "bench loop"])
def test_cuda_is_taken_where_there_is_cuda(name, tmp_path):
    assert build_parser().parse_args(_argv(name, "cuda", tmp_path / "data")).device == "cuda"


@pytest.mark.parametrize("name,default", [("train", "auto"), ("eval", "auto"), ("score", "auto"),
                                          ("bench score", "auto"), ("retrain", "auto"), ("bench loop", "cpu")])
def test_the_default_device_is_unchanged(name, default, tmp_path):
    argv = [a for a in _argv(name, "", tmp_path) if a not in ("--device", "")]
    assert build_parser().parse_args(argv).device == default


def test_auto_and_cpu_parse_without_importing_torch():
    """argparse runs the check on every default too: only cuda may import torch."""
    code = ("import json, sys\n"
            "from orchestrator.cli import build_parser\n"
            "p = build_parser()\n"
            "got = [p.parse_args(a).device for a in (['retrain'], ['retrain', '--device', 'cpu'], "
            "['train', '--device', 'auto'], ['bench', 'loop'], ['eval', '--device', 'cpu'])]\n"
            "p.parse_args(['run', '--retrain-args', '--device auto'])\n"
            "print(json.dumps([got, 'torch' in sys.modules]))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == [["auto", "cpu", "auto", "cpu", "cpu"], False]


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_the_score_bench_refuses_cuda_without_cuda_as_a_config_error():
    """Called as a library, not through the CLI's check: a ConfigError, not torch's AssertionError."""
    with pytest.raises(ConfigError, match="cuda"):
        run_score_bench(members=1, image_size=16, seconds=0.1, batch=1, device="cuda")
