"""What two torch processes on the same cores cost each other: the training step of a small conv net, alone and
two at once, with torch's default threads, with ``OMP_WAIT_POLICY=PASSIVE`` and with one thread each.

The service scores episodes with the champion in its own process while a retrain runs as a subprocess, and
benchmarks share the machine with test runs; each torch process takes as many intra-op threads as the machine
has cores and its OpenMP threads spin while they wait for one another. This times the same fixed work in
each setting, all in one run, and prints each setting's seconds over the default-threads process alone.

Usage: .venv/bin/python bench/torch_threads.py [--steps 3000] [--json out.json]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from jsonout import emit

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


def run(steps: int, n: int, env: dict[str, str]) -> list[dict]:
    procs = [subprocess.Popen([sys.executable, "-c", WORK, str(steps)], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, **env}) for _ in range(n)]
    out = []
    for proc in procs:
        seconds, threads = proc.communicate()[0].split()
        if proc.returncode:
            raise SystemExit(f"a timing process exited {proc.returncode}")
        out.append({"seconds": float(seconds), "threads": int(threads)})
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=3000, help="training steps per process (default 3000)")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args()
    if args.steps < 1:
        p.error(f"--steps must be at least 1, found {args.steps}")
    results = {}
    for name, (n, env) in SETTINGS.items():
        results[name] = run(args.steps, n, env)
    base = results["alone"][0]["seconds"]
    summary = {"cpus": os.cpu_count(), "steps": args.steps,
               "settings": {name: {"threads": r[0]["threads"], "seconds": [round(x["seconds"], 2) for x in r],
                                   "over_alone": round(max(x["seconds"] for x in r) / base, 2)}
                            for name, r in results.items()}}
    return emit(summary, args.json, indent=2)


if __name__ == "__main__":
    sys.exit(main())
