"""What two torch processes on the same cores cost each other: the training step of a small conv net, alone and
two at once, with torch's default threads, with ``OMP_WAIT_POLICY=PASSIVE`` and with one thread each.

The service scores episodes with the champion in its own process while a retrain runs as a subprocess, and
benchmarks share the machine with test runs; each torch process takes as many intra-op threads as the machine
has cores and its OpenMP threads spin while they wait for one another. This times the same fixed work in
each setting, all in one run, and prints each setting's seconds over the default-threads process alone.

Usage: .venv/bin/python bench/torch_threads.py [--steps 3000] [--json out.json]

A timing process that fails (exit status non-zero, or no timing printed) stops the run: the setting, its exit
status and the end of its stderr are printed, exit 1.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from jsonout import emit
from orchestrator.cli.common import Parser

WORK = """
import sys, time, torch
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Conv2d(6, 16, 3, padding=1), torch.nn.SiLU(),
                          torch.nn.Conv2d(16, 32, 3, padding=1, stride=2), torch.nn.SiLU(),
                          torch.nn.Conv2d(32, 3, 3, padding=1))
opt = torch.optim.Adam(net.parameters())
x = torch.rand(32, 6, 16, 16)
start = time.perf_counter()
for _ in range(int(sys.argv[1])):
    opt.zero_grad(); net(x).square().mean().backward(); opt.step()
print(time.perf_counter() - start, torch.get_num_threads())
"""

#: name -> (processes at once, extra environment of each)
SETTINGS = {
    "alone": (1, {}),
    "two at once": (2, {}),
    "passive, alone": (1, {"OMP_WAIT_POLICY": "PASSIVE"}),
    "passive, two at once": (2, {"OMP_WAIT_POLICY": "PASSIVE"}),
    "one thread, alone": (1, {"OMP_NUM_THREADS": "1"}),
    "one thread, two at once": (2, {"OMP_NUM_THREADS": "1"}),
}


class TimingFailed(Exception):
    """A timing process that exited non-zero or printed no timing; the message says which and how it ended."""


def _tail(text: str, lines: int = 20) -> str:
    return "\n".join(text.rstrip().splitlines()[-lines:]) or "(nothing)"


def run(steps: int, n: int, env: dict[str, str], name: str = "alone") -> list[dict]:
    """``n`` timing processes at once with ``env`` added; each one's seconds and torch threads.

    Raises ``TimingFailed`` when one exits non-zero (its exit status checked before its output is read) or
    prints something other than its timing."""
    errs = [tempfile.TemporaryFile("w+") for _ in range(n)]  # (a file, not a pipe: nothing blocks on a full one)
    procs = [subprocess.Popen([sys.executable, "-c", WORK, str(steps)], stdout=subprocess.PIPE, stderr=err,
                              text=True, env={**os.environ, **env}) for err in errs]
    outs = [proc.communicate()[0] for proc in procs]
    out = []
    for proc, stdout, err in zip(procs, outs, errs):
        with err:
            err.seek(0)
            stderr = err.read()
        if proc.returncode:
            raise TimingFailed(f"a timing process of {name!r} exited {proc.returncode}; its stderr ends:\n"
                               f"{_tail(stderr)}")
        try:
            seconds, threads = stdout.split()
            out.append({"seconds": float(seconds), "threads": int(threads)})
        except ValueError:
            raise TimingFailed(f"a timing process of {name!r} printed {stdout[-500:]!r}, not its seconds and "
                               f"threads; its stderr ends:\n{_tail(stderr)}") from None
    return out


def main() -> int:
    p = Parser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=3000, help="training steps per process (default 3000)")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args()
    if args.steps < 1:
        p.error(f"--steps must be at least 1, found {args.steps}")
    if args.json is not None and (args.json.is_dir() or not args.json.parent.is_dir()):
        p.error(f"--json {args.json}: expected a file in an existing directory")
    results = {}
    for name, (n, env) in SETTINGS.items():
        try:
            results[name] = run(args.steps, n, env, name)
        except TimingFailed as exc:
            print(f"{p.prog}: {exc}", file=sys.stderr)
            return 1
    base = results["alone"][0]["seconds"]
    summary = {"cpus": os.cpu_count(), "steps": args.steps,
               "settings": {name: {"threads": r[0]["threads"], "seconds": [round(x["seconds"], 2) for x in r],
                                   "over_alone": round(max(x["seconds"] for x in r) / base, 2)}
                            for name, r in results.items()}}
    return emit(summary, args.json, indent=2)


if __name__ == "__main__":
    sys.exit(main())
