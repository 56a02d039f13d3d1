"""Soak check of "the service runs unattended": the whole loop for a long while, watching for leaks.

Pins a small eval split, starts ``activecollect serve`` (active planner, retrains every
--retrain-every stored episodes in a child process, dashboard on) and --workers workers as real
subprocesses over loopback, and lets them run for --minutes. Every --interval seconds it samples

- the service's and each worker's resident memory (RSS), open file descriptors and threads;
- the service's child processes (retrain jobs) and any of them left a zombie;
- the catalog's SQLite write-ahead log size (a reader that never lets go makes it grow without end);
- the queue by status, the episodes, the models and the champion;
- the dashboard (``/metrics`` and ``/api/stats``) and the admin plane (``activecollect stats``): each
  must answer.

Then it SIGTERMs the workers (each finishes its episode) and the service, and audits the data
directory with ``bench/chaos.py``'s checks: every indexed episode's file is there with its sha256,
``episodes verify`` passes, a done request has exactly its one episode, no request is left leased, no
stray file.

Growth is judged after a warm-up (--warmup-minutes, and the first champion's load): between
the median of the first three and of the last three samples after it. The run fails (exit 1) when
the service's file descriptors grow by more than 16 or its threads by more than 8, a worker's RSS
by more than 25 %, the service's RSS by more than --rss-growth (default 25 %), the WAL passes 64 MiB,
a zombie child outlives a sampling interval, the dashboard or the admin plane stops answering, no
episode comes in for --stall-minutes, the service logs an error (a failed retrain does) or exits, or
an audit check fails. Exit 2 for a usage error. Process logs go to DATA/chaos-logs/.

Usage: .venv/bin/python bench/soak.py --data /tmp/soak1 [--minutes 30] [--workers 2]
       [--retrain-every 96] [--interval 15] [--json summary.json]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from pathlib import Path

import numpy as np

from chaos import (ACTIVECOLLECT, Cluster, check_episode_rows, check_files, exit_on_sigterm, free_port, log, read_rows,
                   request_counts)
from orchestrator.cli.common import Parser, trainable_image_size
from storage.database import DB_NAME
from storage.records import TRAINABLE_SIZES
from workers import flags

RETRAIN_ARGS = ("--members 3 --epochs 2 --widths 8,16,32 --batch-size 16 --max-windows 1500 --from-champion "
                "--device cpu --min-improvement 0.005")
WAL_LIMIT = 64 << 20
FD_GROWTH, THREAD_GROWTH, WORKER_RSS_GROWTH = 16, 8, 0.25


def proc_stats(pid: int) -> dict | None:
    """RSS (MiB), threads and open descriptors of a live process; None once it is gone."""
    try:
        fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                      if ":" in line)
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError):
        return None
    if "VmRSS" not in fields:  # a zombie: exited, not yet waited for
        return None
    return {"rss_mib": int(fields["VmRSS"].split()[0]) / 1024, "threads": int(fields["Threads"]), "fds": fds}


def children(pid: int) -> tuple[int, list[int]]:
    """(child processes, the pids of the zombies among them) of ``pid``."""
    n, zombies = 0, []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            stat = Path(entry.path, "stat").read_text()
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]  # the command name may hold spaces and ')'
        if int(ppid) == pid:
            n += 1
            if state == "Z":
                zombies.append(int(entry.name))
    return n, zombies


def catalog_counts(data: Path) -> dict:
    """Episodes by split, models by status and the champion, read-only; {} while the catalog is busy."""
    try:
        con = sqlite3.connect(f"file:{data / DB_NAME}?mode=ro", uri=True, timeout=5)
        try:
            eps = dict(con.execute("SELECT split, COUNT(*) FROM episodes GROUP BY split"))
        finally:
            con.close()
    except sqlite3.Error:
        return {}
    models = data / "models"
    versions = [p for p in models.iterdir() if p.is_dir() and not p.name.startswith(".")] if models.is_dir() else []
    return {"episodes": eps, "models": len(versions)}  # (a retrain stages its checkpoint in a dot folder)


def disk_mib(data: Path) -> dict[str, float]:
    """MiB on disk under each of the data directory's parts (what grows with running time)."""
    parts = {"episodes": data / "episodes", "models": data / "models", "logs": data / "logs",
             "catalog": data / DB_NAME}
    out = {}
    for name, path in parts.items():
        files = [path] if path.is_file() else list(path.rglob("*")) if path.is_dir() else []
        out[name] = round(sum(f.stat().st_size for f in files if f.is_file()) / 2**20, 2)
    return out


def answers(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=10) as reply:
            return reply.status == 200 and bool(reply.read())
    except OSError:
        return False


class Soak:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.port = free_port()
        service_args = ("--planner", "active", "--seed-requests", str(2 * args.workers), "--steps", str(args.steps),
                        "--retrain-every", str(args.retrain_every), f"--retrain-args={args.retrain_args}",
                        "--dashboard-port", str(self.port))
        self.cluster = Cluster(args.data, args.realtime, args.workers, service_args, args.size)
        self.samples: list[dict] = []
        self.failure = ""
        """Why the run ended early ('' when it ran its time)."""

    def sample(self, t: float) -> dict:
        c = self.cluster
        wal = c.data / (DB_NAME + "-wal")
        kids, zombies = children(c.service.pid)
        stats = c.admin("stats", "--json", "--timeout", "10")
        dash = f"http://127.0.0.1:{self.port}"
        s = {"t_min": round(t / 60, 2), "service": proc_stats(c.service.pid),
             "workers": {w: proc_stats(p.pid) for w, p in c.workers.items()},
             "children": kids, "zombies": zombies, "wal_mib": wal.stat().st_size / 2**20 if wal.exists() else 0.0,
             "requests": dict(request_counts(c.data)), **catalog_counts(c.data),
             "dashboard_ok": answers(dash + "/metrics") and answers(dash + "/api/stats"),
             "admin_ok": stats.returncode == 0}
        self.samples.append(s)
        sv = s["service"] or {}
        log(f"{s['t_min']:6.1f} min  service rss {sv.get('rss_mib', 0):6.1f} MiB fds {sv.get('fds')} "
            f"threads {sv.get('threads')}  children {kids}  wal {s['wal_mib']:.1f} MiB  "
            f"episodes {s.get('episodes')}  models {s.get('models')}  requests {s['requests']}")
        return s

    def run(self) -> None:
        a = self.args
        r = subprocess.run([ACTIVECOLLECT, "eval-split", "create", "--data", str(a.data), "--episodes",
                            str(a.eval_episodes), "--size", str(a.size), "--steps", str(a.steps)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"eval-split create failed: {r.stderr.strip()}")
        self.cluster.start_service()
        for wid in self.cluster.worker_ids:
            self.cluster.start_worker(wid)
        t0 = time.monotonic()
        while (t := time.monotonic() - t0) < a.minutes * 60:
            for name, p in [("service", self.cluster.service), *self.cluster.workers.items()]:
                if p.poll() is not None:
                    self.failure = f"{name} exited with {p.returncode} at {t / 60:.1f} min; see {self.cluster.logs}"
                    return
            self.sample(t)
            time.sleep(max(0.0, a.interval - (time.monotonic() - t0 - t)))
        self.cluster.stop()


def growth(samples: list[dict], get) -> dict:
    """First (median of three), last (median of three) and max of ``get(sample)`` over ``samples``."""
    values = [v for v in map(get, samples) if v is not None]
    if not values:
        return {"first": None, "last": None, "max": None}
    return {"first": round(float(np.median(values[:3])), 2), "last": round(float(np.median(values[-3:])), 2),
            "max": round(max(values), 2)}


def longest_stall(samples: list[dict]) -> tuple[float, float] | None:
    """(from, to) minutes of the longest stretch without a new episode (samples without counts skipped)."""
    counted = [(s["t_min"], sum(s["episodes"].values())) for s in samples if s.get("episodes")]
    best, since = None, None
    for (t0, n0), (t1, n1) in zip(counted, counted[1:]):
        since = t0 if since is None else since
        if n1 > n0:
            since = None
        elif best is None or t1 - since > best[1] - best[0]:
            best = (since, t1)
    return best


def warm_samples(samples: list[dict], warmup_minutes: float, least: int = 6) -> list[dict]:
    """The samples growth is judged on: from ``warmup_minutes`` on and, where at least ``least`` samples are left
    after it, from the sample after the first that counts a model (the service imports torch and loads the first
    champion when it first scores after the first promotion: a step of ~300 MiB, not growth)."""
    warm = [s for s in samples if s["t_min"] >= warmup_minutes]
    first_model = next((s["t_min"] for s in samples if s.get("models")), None)
    after = [] if first_model is None else [s for s in warm if s["t_min"] > first_model]
    return after if len(after) >= least else warm


def summarize(soak: Soak, elapsed: float) -> dict:
    a, data = soak.args, soak.args.data
    warm = warm_samples(soak.samples, a.warmup_minutes)
    problems = [soak.failure] if soak.failure else []
    if len(warm) < 6:
        problems.append(f"only {len(warm)} samples after the warm-up; run longer or sample more often")
    svc = {k: growth(warm, lambda s, k=k: (s["service"] or {}).get(k)) for k in ("rss_mib", "fds", "threads")}
    workers = {w: growth(warm, lambda s, w=w: (s["workers"].get(w) or {}).get("rss_mib"))
               for w in soak.cluster.worker_ids}
    if len(warm) >= 6:
        if svc["fds"]["last"] - svc["fds"]["first"] > FD_GROWTH:
            problems.append(f"service file descriptors grew {svc['fds']['first']} -> {svc['fds']['last']}")
        if svc["threads"]["last"] - svc["threads"]["first"] > THREAD_GROWTH:
            problems.append(f"service threads grew {svc['threads']['first']} -> {svc['threads']['last']}")
        if svc["rss_mib"]["last"] > svc["rss_mib"]["first"] * (1 + a.rss_growth):
            problems.append(f"service RSS grew {svc['rss_mib']['first']} -> {svc['rss_mib']['last']} MiB")
        for w, g in workers.items():
            if g["first"] and g["last"] > g["first"] * (1 + WORKER_RSS_GROWTH):
                problems.append(f"worker {w} RSS grew {g['first']} -> {g['last']} MiB")
    if (stall := longest_stall(soak.samples)) and stall[1] - stall[0] > a.stall_minutes:
        problems.append(f"no episode was collected from {stall[0]:.1f} to {stall[1]:.1f} min")
    # A child that has just exited is a zombie until the scheduler reaps it (it looks every 0.5 s):
    # one left unreaped is the same pid in two samples in a row.
    lingering = {z for s0, s1 in zip(soak.samples, soak.samples[1:]) for z in set(s0["zombies"]) & set(s1["zombies"])}
    if lingering:
        problems.append(f"zombie children never reaped: {sorted(lingering)}")
    if (wal := max((s["wal_mib"] for s in soak.samples), default=0.0)) > WAL_LIMIT / 2**20:
        problems.append(f"the WAL reached {wal:.0f} MiB")
    for what in ("dashboard_ok", "admin_ok"):
        if failed := sum(not s[what] for s in soak.samples):
            problems.append(f"{what.split('_')[0]} did not answer in {failed} of {len(soak.samples)} samples")
    reqs, eps = read_rows(data)
    con = sqlite3.connect(data / DB_NAME)
    try:
        models = [status + (" (pruned)" if pruned else "") for status, pruned in
                  con.execute("SELECT status, pruned_at IS NOT NULL FROM models")]
    except sqlite3.OperationalError:  # no retrain ever opened the registry
        models = []
    finally:
        con.close()
    problems += check_episode_rows(reqs, eps)
    if leased := sum(r["status"] == "leased" for r in reqs.values()):
        problems.append(f"{leased} requests still leased after the workers finished")
    file_problems, notes = check_files(data, eps)
    slogs = "".join(p.read_text(errors="replace") for p in soak.cluster.logs.glob("service.*.log"))
    if errors := [line for line in slogs.splitlines() if " ERROR " in line]:  # failed retrains log one too
        problems.append(f"{len(errors)} errors in the service log, the first: {errors[0][:300]}")
    retrain_logs = sorted((data / "logs").glob("retrain-*.log")) if (data / "logs").is_dir() else []
    return {
        "minutes": a.minutes, "interval_s": a.interval, "workers": a.workers, "size": a.size, "steps": a.steps,
        "retrain_every": a.retrain_every, "retrain_args": a.retrain_args, "elapsed_s": round(elapsed, 1),
        "episodes": Counter(e["split"] for e in eps), "requests": dict(Counter(r["status"] for r in reqs.values())),
        "requests_by_planner": dict(Counter(json.loads(r["reason"]).get("planner") for r in reqs.values())),
        "models": dict(Counter(models)), "retrain_jobs": len(retrain_logs),
        "service_errors_logged": len(errors), "service": svc, "worker_rss_mib": workers,
        "wal_mib_max": round(wal, 2), "disk_mib": disk_mib(data), "samples": len(soak.samples),
        "warm_samples": len(warm),
        "problems": problems + file_problems, "notes": notes, "series": soak.samples,
    }


def main(argv=None) -> int:
    p = Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, metavar="DIR",
                   help="new or empty directory: the service's data directory (process logs in DATA/chaos-logs/)")
    p.add_argument("--minutes", type=float, default=30.0, help="how long the loop runs (default 30)")
    p.add_argument("--warmup-minutes", type=float, default=None,
                   help="growth is judged after this (default a fifth of --minutes)")
    p.add_argument("--interval", type=float, default=15.0, metavar="S", help="seconds between samples (default 15)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--size", type=trainable_image_size, default=32, metavar="PX",
                   help=f"frame size, {TRAINABLE_SIZES} (default 32)")
    p.add_argument("--steps", type=int, default=30, help="steps per episode (default 30)")
    p.add_argument("--eval-episodes", type=int, default=8, help="episodes in the eval split (default 8)")
    p.add_argument("--realtime", type=flags.realtime, default=1.0, metavar="X",
                   help="workers' --realtime (default 1: an episode takes steps / 10 s)")
    p.add_argument("--retrain-every", type=int, default=96, metavar="N",
                   help="retrain each time N more episodes are stored (default 96)")
    p.add_argument("--retrain-args", default=RETRAIN_ARGS, metavar="'ARGS'",
                   help=f"serve's --retrain-args (default '{RETRAIN_ARGS}')")
    p.add_argument("--stall-minutes", type=float, default=3.0, metavar="M",
                   help="longest allowed stretch without a new episode (default 3)")
    p.add_argument("--rss-growth", type=float, default=0.25, metavar="F",
                   help="largest allowed relative growth of the service's RSS after the warm-up (default 0.25)")
    p.add_argument("--json", type=Path, metavar="FILE", help="also write the summary (with every sample) here")
    a = p.parse_args(argv)
    if a.minutes <= 0 or a.interval <= 0 or a.workers < 1 or a.retrain_every < 1:
        p.error("--minutes, --interval, --workers and --retrain-every must be positive")
    if a.warmup_minutes is None:
        a.warmup_minutes = a.minutes / 5
    if a.data.exists() and (not a.data.is_dir() or any(a.data.iterdir())):
        print(f"soak: {a.data} is not an empty directory; give a new or empty one", file=sys.stderr)
        return 2
    log(f"data {a.data}, {a.minutes:g} min")
    soak = Soak(a)
    t0 = time.monotonic()
    signal.signal(signal.SIGTERM, exit_on_sigterm)  # the service and workers are in sessions of their own
    try:
        soak.run()
    finally:
        soak.cluster.kill_all()
    summary = summarize(soak, time.monotonic() - t0)
    text = json.dumps(summary, indent=1, default=str)
    if a.json:
        a.json.write_text(text)
    brief = {k: v for k, v in summary.items() if k != "series"}
    print(json.dumps(brief, indent=1, default=str))
    s = summary
    log(f"{s['elapsed_s']} s: {sum(s['episodes'].values())} episodes, {s['retrain_jobs']} retrains {s['models']}, "
        f"service rss {s['service']['rss_mib']}, fds {s['service']['fds']}: "
        + ("NO LEAK SEEN" if not s["problems"] else f"PROBLEMS ({len(s['problems'])})"))
    return 1 if s["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
