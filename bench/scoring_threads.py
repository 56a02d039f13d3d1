"""Scoring beside a retrain: what the service's scoring threads and a retrain job cost each other.

``serve`` scores every stored episode with the champion in its own process while each retrain runs
as a child process (``activecollect retrain``), by default with a thread per core. This times, in one
run and in turn (the order rotated each repeat):

- a retrain alone: wall seconds of ``activecollect retrain --data COPY ARGS`` on a fresh copy of a
  snapshot of DATA (``activecollect backup``; every job trains the same thing, DATA is never changed),
  with torch's default threads and with the cores the scorer leaves
  (``retrain --threads max(1, cores - --threads)``, "fitted": what ``serve`` gives its jobs by default);
- the scorer alone for --score-seconds, with torch's default threads and with --threads: episodes
  scored per second;
- the retrain with the scorer busy beside it: both default; the scorer at --threads and the retrain
  default; both fitted to the cores.

The scorer is ``orchestrator.champion.ChampionScorer`` with its ``threads`` setting (what ``serve
--scoring-threads`` sets), scoring DATA's training episodes back to back: a fleet that keeps it busy,
the worst case (two workers at real time keep it busy about 1 % of the time). Figures are medians
over --repeats, and ratios to the alone figures of the same run.

With --rate the scorer is paced as a fleet's uploads arrive (one episode every 1/rate s) instead: the usual
case, where it is busy a few per cent of the time; the figures then say what the retrain pays for its threads.

Usage: .venv/bin/python bench/scoring_threads.py --data DIR [--repeats 3] [--threads 1] [--rate EPS]
       [--score-seconds 10] [--retrain-args 'ARGS'] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from jsonout import emit
from orchestrator.companions import fitted_retrain_threads

ROOT = Path(__file__).resolve().parents[1]
RETRAIN_ARGS = "--members 4 --epochs 6 --widths 8,16,32 --max-windows 1200 --from-champion --device cpu"
#: Every child's environment: without OMP_NUM_THREADS, so "default" is torch's own choice.
ENV = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}

SCORER = """
import json, sys, threading, time
from orchestrator.champion import ChampionScorer
from storage.catalog import Catalog
data, threads, rate = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
catalog = Catalog(data)
episodes = [catalog.load(row.episode_id) for row in catalog.list(split="train", limit=50)]
scorer = ChampionScorer(data, threads=threads)
if not episodes or scorer(episodes[0]) is None:
    sys.exit("no champion or no training episode to score")
import torch
print("ready", flush=True)
sys.stdin.readline()  # go
stop = threading.Event()
threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
n, start = 0, time.perf_counter()
busy = 0.0
while not stop.is_set():
    begin = time.perf_counter()
    scorer(episodes[n % len(episodes)])
    busy += time.perf_counter() - begin
    n += 1
    if rate:  # a fleet's pace: the next episode arrives n / rate after the start
        stop.wait(max(0.0, start + n / rate - time.perf_counter()))
print(json.dumps({"episodes": n, "seconds": time.perf_counter() - start, "busy_s": busy,
                  "threads": torch.get_num_threads()}))
"""


class Scorer:
    """A scoring process, loaded and waiting; ``go()`` starts it, ``stop()`` returns its episodes per second
    (``rate``: at most that many, one every 1/rate s, as a fleet's uploads arrive; 0: back to back)."""

    def __init__(self, data: Path, threads: int, rate: float = 0.0) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", SCORER, str(data), str(threads), str(rate)], cwd=ROOT,
                                     env=ENV,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if self.proc.stdout.readline().strip() != "ready":
            self.proc.kill()
            raise SystemExit(f"scoring_threads.py: the scorer did not start (exit {self.proc.wait()})")
        self.threads = None
        self.busy_share = None
        """The share of the time it spent scoring (1.0 back to back)."""

    def go(self) -> None:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()

    def stop(self) -> float:
        out, _ = self.proc.communicate("stop\n", timeout=120)
        result = json.loads(out.strip().splitlines()[-1])
        self.threads = result["threads"]
        self.busy_share = result["busy_s"] / result["seconds"]
        return result["episodes"] / result["seconds"]


def snapshot(data: Path, dest: Path) -> None:
    """A consistent copy of ``data`` (``activecollect backup``: the catalog may be open in another process)."""
    proc = subprocess.run([sys.executable, "-m", "orchestrator", "backup", str(dest), "--data", str(data)],
                          cwd=ROOT, capture_output=True, text=True, env=ENV)
    if proc.returncode != 0:
        raise SystemExit(f"scoring_threads.py: could not copy {data}: {proc.stderr.strip()}")


def retrain(template: Path, args: list[str], threads: int) -> float:
    """Wall seconds of one retrain job on a fresh copy of ``template`` (a snapshot nothing else opens), with
    ``retrain --threads threads`` (0: torch's default)."""
    args = [*args, "--threads", str(threads)]
    with tempfile.TemporaryDirectory(prefix="scoring-threads-") as tmp:
        copy = Path(tmp) / "data"
        shutil.copytree(template, copy)
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "orchestrator", "retrain", "--data", str(copy), *args],
                              cwd=ROOT, capture_output=True, text=True, env=ENV)
        seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"scoring_threads.py: the retrain failed (exit {proc.returncode}): "
                         f"{proc.stderr.strip().splitlines()[-1:] or ''}")
    return seconds


def settings(threads: int) -> dict[str, tuple[int | None, int | None]]:
    """name -> (the scorer's threads, the retrain's threads); None: not run, 0: torch's default (one per core).
    "fitted": the retrain takes the cores the scorer leaves, as ``serve`` gives its jobs by default."""
    fitted = fitted_retrain_threads(threads)
    return {"retrain alone": (None, 0), f"retrain alone, {fitted} threads (fitted)": (None, fitted),
            "scorer alone": (0, None), f"scorer alone, {threads} threads": (threads, None),
            "both default threads": (0, 0), f"scorer {threads} threads, retrain default": (threads, 0),
            f"scorer {threads} threads, retrain {fitted} (fitted)": (threads, fitted)}


def measure(data: Path, template: Path, scorer_threads: int | None, retrain_threads: int | None,
            score_seconds: float, retrain_args: list[str], rate: float = 0.0) -> dict:
    """One setting once: {"retrain_s": ...} and/or {"scored_per_s": ..., "threads": the scorer's, "busy_share":
    the share of its time it scored}. The scorer reads ``data`` (at ``rate``), the retrain a copy of ``template``."""
    if scorer_threads is None:
        return {"retrain_s": retrain(template, retrain_args, retrain_threads)}
    scorer = Scorer(data, scorer_threads, rate)
    scorer.go()
    if retrain_threads is None:
        time.sleep(score_seconds)
        out = {}
    else:
        out = {"retrain_s": retrain(template, retrain_args, retrain_threads)}
    scored = scorer.stop()
    return {**out, "scored_per_s": scored, "threads": scorer.threads, "busy_share": scorer.busy_share}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, metavar="DIR",
                   help="a data directory with a champion and a pinned eval split (what `make run` leaves)")
    p.add_argument("--threads", type=int, default=1, help="the scorer's threads to compare with torch's default "
                                                          "(default 1, serve's default)")
    p.add_argument("--repeats", type=int, default=3, help="times each setting is measured (default 3)")
    p.add_argument("--score-seconds", type=float, default=10.0, metavar="S",
                   help="how long the scorer alone is timed (default 10)")
    p.add_argument("--retrain-args", default=RETRAIN_ARGS, metavar="'ARGS'",
                   help=f"arguments of each retrain job (default '{RETRAIN_ARGS}': run's, without its gate)")
    p.add_argument("--rate", type=float, default=0.0, metavar="EPS",
                   help="the scorer scores at most EPS episodes per second, as a fleet's uploads arrive (default 0: "
                        "back to back, the worst case; two workers at real time upload about 0.66)")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args()
    if args.threads < 1 or args.repeats < 1 or not args.score_seconds > 0 or args.rate < 0:
        p.error("--threads and --repeats must be at least 1, --score-seconds positive and --rate not negative")
    if not (args.data / "catalog.sqlite").is_file():
        p.error(f"no catalog in {args.data}: give the data directory of a `make run` (or a soak)")
    cores = len(os.sched_getaffinity(0))
    plan = settings(args.threads)
    names = list(plan)
    runs: dict[str, list[dict]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory(prefix="scoring-threads-") as tmp:
        template = Path(tmp) / "data"
        snapshot(args.data, template)
        for rep in range(args.repeats):
            for name in names[rep % len(names):] + names[:rep % len(names)]:
                runs[name].append(measure(args.data, template, *plan[name], args.score_seconds,
                                          shlex.split(args.retrain_args), args.rate))
                print(f"{name}: {runs[name][-1]}", file=sys.stderr, flush=True)
    median = {name: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for name, rs in runs.items()}
    alone_scoring = {m["threads"]: m["scored_per_s"] for name, m in median.items() if plan[name][1] is None}
    summary = {"data": str(args.data), "cores": cores, "repeats": args.repeats, "retrain_args": args.retrain_args,
               "rate": args.rate, "settings": {}}
    for name in names:
        m = median[name]
        summary["settings"][name] = {
            **{k: round(v, 4 if k == "busy_share" else 2) for k, v in m.items()},
            **({"retrain_over_alone": round(m["retrain_s"] / median["retrain alone"]["retrain_s"], 2)}
               if "retrain_s" in m else {}),
            **({"scoring_over_alone": round(m["scored_per_s"] / alone_scoring[m["threads"]], 2)}
               if "scored_per_s" in m else {}),
            "each": runs[name]}
    return emit(summary, args.json)


if __name__ == "__main__":
    sys.exit(main())
