"""What the service's heap trimming (``orchestrator.heap.HeapTrimmer``) does to its memory and its planning speed.

One child process per setting plays DATA's training episodes (loaded up front) through the active planner
that ``serve`` builds (``ChampionScorer`` with 1 thread, the default ``ActivePlannerConfig``), one episode a
batch as a real-time fleet uploads them, and samples its resident memory (VmRSS) every 50 episodes:

- no trim: glibc's default, whose mmap threshold rises as large blocks are freed;
- a trim after every episode (``HeapTrimmer(0)``);
- a trim at most every --interval seconds after an episode (what ``serve`` does, every 5 s by default);
- no trim, but a fixed mmap threshold (``MALLOC_MMAP_THRESHOLD_=131072``: no rising threshold).

Episodes planned per second are a ratio to the no-trim child of the same repeat; the settings run in turn,
--repeats times, and the figures are medians.

Usage: .venv/bin/python bench/heap_trim.py --data DIR [--episodes 600] [--interval 1] [--repeats 2] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from jsonout import emit

ROOT = Path(__file__).resolve().parents[1]

CHILD = """
import json, sys, time
import numpy as np
from orchestrator.champion import ChampionScorer
from orchestrator.heap import HeapTrimmer
from orchestrator.planner import ActivePlanner, ActivePlannerConfig
from storage.catalog import Catalog
data, episodes, interval = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
def rss_mib():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS"))
catalog = Catalog(data)
eps = [catalog.load(row.episode_id) for row in catalog.list(split="train", limit=episodes)]
scorer = ChampionScorer(data, threads=1)
if not eps or scorer(eps[0]) is None:
    sys.exit("no champion or no training episode to plan from")
planner = ActivePlanner(ActivePlannerConfig(), scorer, np.random.default_rng(0))
trim = HeapTrimmer(interval) if interval >= 0 else None
samples, start = [], time.perf_counter()
for i, ep in enumerate(eps):
    planner.plan([ep])
    if trim is not None:
        trim()
    if i % 50 == 0 or i == len(eps) - 1:
        samples.append([i, round(rss_mib(), 1)])
seconds = time.perf_counter() - start
print(json.dumps({"episodes": len(eps), "per_s": len(eps) / seconds, "rss": samples,
                  "trims": trim.trims if trim else 0}))
"""


def settings(interval: float) -> dict[str, tuple[float, dict[str, str]]]:
    """name -> (the trimmer's interval, -1 for none; extra environment)."""
    return {"no trim": (-1.0, {}), "trim after every episode": (0.0, {}),
            f"trim at most every {interval:g} s": (interval, {}),
            "no trim, MALLOC_MMAP_THRESHOLD_=131072": (-1.0, {"MALLOC_MMAP_THRESHOLD_": "131072"})}


def run(data: Path, episodes: int, interval: float, env: dict[str, str]) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(data), str(episodes), str(interval)], cwd=ROOT,
                          env={**os.environ, **env}, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"heap_trim.py: a child failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, metavar="DIR",
                   help="a data directory with a champion (what `make run` or a soak leaves)")
    p.add_argument("--episodes", type=int, default=600, help="training episodes planned (default 600)")
    p.add_argument("--interval", type=float, default=1.0, metavar="S",
                   help="the interval of the third setting (default 1: this loop plans ~30 episodes a second)")
    p.add_argument("--repeats", type=int, default=2, help="times each setting is run (default 2)")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args()
    if args.episodes < 2 or args.repeats < 1 or not args.interval > 0:
        p.error("--episodes must be at least 2, --repeats at least 1 and --interval positive")
    if not (args.data / "catalog.sqlite").is_file():
        p.error(f"no catalog in {args.data}: give the data directory of a `make run` (or a soak)")
    plan = settings(args.interval)
    runs: dict[str, list[dict]] = {name: [] for name in plan}
    for _ in range(args.repeats):
        for name, (interval, env) in plan.items():
            runs[name].append(run(args.data, args.episodes, interval, env))
            print(f"{name}: {runs[name][-1]['per_s']:.1f} episodes/s, rss {runs[name][-1]['rss']}",
                  file=sys.stderr, flush=True)
    summary = {"data": str(args.data), "repeats": args.repeats, "settings": {}}
    for name, rs in runs.items():
        ratios = [r["per_s"] / base["per_s"] for r, base in zip(rs, runs["no trim"])]
        summary["settings"][name] = {
            "episodes": rs[0]["episodes"], "per_s": round(statistics.median(r["per_s"] for r in rs), 1),
            "per_s_over_no_trim": round(statistics.median(ratios), 3),
            "rss_first_mib": statistics.median(r["rss"][0][1] for r in rs),
            "rss_max_mib": statistics.median(max(s[1] for s in r["rss"]) for r in rs),
            "rss_last_mib": statistics.median(r["rss"][-1][1] for r in rs),
            "trims": statistics.median(r["trims"] for r in rs), "each": rs}
    return emit(summary, args.json)


if __name__ == "__main__":
    sys.exit(main())
