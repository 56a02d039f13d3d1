"""Chaos check of the promise "nothing acknowledged is ever lost": SIGKILL the service mid-work, then audit.

Starts ``activecollect serve`` on a free loopback port and three workers (``workers.agent``) as real
subprocesses, and enqueues --requests requests from two threads with ``activecollect queue add``
(each with its own idempotency key, retried until acknowledged). Meanwhile, --kills times, once at
least one more request has moved and a random dwell has passed, it SIGKILLs the service, waits a
random moment and starts it again. The kills cycle through --triggers:

- ``random``: whenever the dwell ends;
- ``tmp``: the moment a staging file (``.<id>.mcap.*.tmp``) appears under ``episodes/``;
- ``mcap``: the moment a new ``.mcap`` is renamed into place (maybe not yet committed);
- ``mcap-all``: as ``mcap``, and every worker is SIGKILLed too (the whole machine goes).

Before --worker-kills of the service kills, a random worker is SIGKILLed and restarted as well.
Then the queue drains, workers and service stop with SIGTERM, and the data directory is checked:

1. every acknowledged request is in the catalog, nothing else is, idempotency keys are unique;
2. every request ended done, dead or cancelled (none queued or leased);
3. a done request has exactly the one episode it names, any other request none, and every train
   episode names a done request;
4. every indexed episode's file exists and has its recorded sha256; ``activecollect episodes
   verify`` passes;
5. no unindexed ``*.mcap`` under ``episodes/`` (``serve`` moves those to ``orphans/`` at start-up),
   no staging file older than ``storage.catalog.STAGING_MAX_AGE_S`` (younger ones are noted only: the
   service deletes them on a later sweep), no other ``*.tmp`` file anywhere in the data directory.

Exit status 0 when every invariant holds, 1 otherwise, 2 for a usage error. Process logs go to
DATA/chaos-logs/.

Usage: .venv/bin/python bench/chaos.py --data /tmp/chaos1 [--requests 150] [--kills 9]
       [--worker-kills 2] [--seed S] [--steps 20] [--realtime 0.5] [--upload-part-kb KB] [--triggers random,tmp,mcap]
       [--json summary.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from orchestrator.cli.common import Parser
from storage.catalog import ORPHANS_DIR, STAGING_MAX_AGE_S
from storage.database import DB_NAME
from workers import flags

REPO = Path(__file__).resolve().parents[1]
ACTIVECOLLECT = str(Path(sys.executable).parent / "activecollect")
LOGS = "chaos-logs"
TRIGGERS = ("random", "tmp", "mcap", "mcap-all")
SHAPES = ("T", "box", "L", "disk")
T0 = time.monotonic()


def log(*parts) -> None:
    print(f"[{time.monotonic() - T0:7.1f}s]", *parts, file=sys.stderr, flush=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def episode_names(data: Path) -> set[str]:
    """File names in every shard directory under DATA/episodes/."""
    out: set[str] = set()
    try:
        for shard in os.scandir(data / "episodes"):
            if shard.is_dir():
                out.update(e.name for e in os.scandir(shard.path))
    except FileNotFoundError:
        pass
    return out


def request_counts(data: Path) -> Counter:
    """Requests by status, read from the catalog without writing; empty while it cannot be read."""
    try:
        con = sqlite3.connect(f"file:{data / DB_NAME}?mode=ro", uri=True, timeout=5)
        try:
            return Counter(dict(con.execute("SELECT status, COUNT(*) FROM requests GROUP BY status")))
        finally:
            con.close()
    except sqlite3.Error:
        return Counter()


class Cluster:
    """The service and the workers as subprocesses, each start with its own log file."""

    def __init__(self, data: Path, realtime: float, n_workers: int = 3,
                 service_args: tuple[str, ...] = ("--planner", "none", "--dashboard-port", "-1"),
                 worker_size: int = 16, worker_args: tuple[str, ...] = ()) -> None:
        self.data, self.realtime, self.worker_args = data, realtime, worker_args
        self.service_args, self.worker_size = service_args, worker_size
        self.logs = data / LOGS
        self.logs.mkdir(parents=True)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.service: subprocess.Popen | None = None
        self.service_starts = 0
        self.workers: dict[str, subprocess.Popen] = {}
        self.worker_starts: Counter = Counter()
        self.worker_ids = [f"w{i}" for i in range(1, n_workers + 1)]

    def _spawn(self, argv: list[str], name: str, cwd: Path) -> subprocess.Popen:
        with open(self.logs / f"{name}.log", "wb") as f:
            return subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, cwd=cwd, start_new_session=True)

    def start_service(self, timeout: float = 60.0) -> None:
        """Starts ``serve`` and returns once ``stats`` answers (after its start-up sweep)."""
        self.service_starts += 1
        self.service = self._spawn([ACTIVECOLLECT, "serve", "--data", str(self.data), "--init", "--listen",
                                    self.endpoint, *self.service_args, "--log-level", "INFO"],
                                   f"service.{self.service_starts}", self.data)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.service.poll() is not None:
                raise SystemExit(f"service exited with {self.service.returncode}; see {self.logs}")
            if self.admin("stats", "--json", "--timeout", "2").returncode == 0:
                log(f"service #{self.service_starts} ready (pid {self.service.pid})")
                return
            time.sleep(0.3)
        raise SystemExit(f"service did not answer within {timeout:g} s; see {self.logs}")

    def admin(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run([ACTIVECOLLECT, *args, "--connect", self.endpoint], capture_output=True, text=True)

    def start_worker(self, wid: str) -> None:
        self.worker_starts[wid] += 1
        self.workers[wid] = self._spawn([sys.executable, "-m", "workers.agent", "--connect", self.endpoint,
                                         "--size", str(self.worker_size), "--id", wid,
                                         "--realtime", str(self.realtime), *self.worker_args],
                                        f"worker.{wid}.{self.worker_starts[wid]}", REPO)

    def kill(self, proc: subprocess.Popen, what: str) -> None:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        log(f"SIGKILL {what}")

    def stop(self) -> None:
        """SIGTERM the workers (they finish their episode), then the service; SIGKILL what lingers."""
        procs = list(self.workers.values()) + ([self.service] if self.service else [])
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()

    def kill_all(self) -> None:
        for p in list(self.workers.values()) + ([self.service] if self.service else []):
            if p.poll() is None:
                p.kill()
                p.wait()


class Chaos:
    """One run: enqueue, kill on schedule, drain; ``acked`` maps idempotency key to request id."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.rng = np.random.default_rng(args.seed)
        self.cluster = Cluster(args.data, args.realtime, worker_args=(
            () if args.upload_part_kb is None else ("--upload-part-kb", str(args.upload_part_kb))))
        self.acked: dict[str, str] = {}
        self.lock = threading.Lock()
        self.enqueue_retries = 0
        self.events: list[str] = []

    def work_left(self, counts: Counter) -> bool:
        return len(self.acked) < self.args.requests or counts["queued"] + counts["leased"] > 0

    def enqueue(self, keys: list[tuple[str, int]]) -> None:
        """``queue add`` each (key, seed) until acknowledged; a retry of an acknowledged add is a no-op."""
        for key, seed in keys:
            while True:
                r = self.cluster.admin("queue", "add", "--json", "--shape", SHAPES[seed % 4], "--policy", "push",
                                       "--seed", str(seed), "--steps", str(self.args.steps),
                                       "--idempotency-key", key, "--timeout", "5")
                if r.returncode == 0:
                    with self.lock:
                        self.acked[key] = json.loads(r.stdout)["request"]["id"]
                    break
                with self.lock:
                    self.enqueue_retries += 1
                time.sleep(0.5)  # the service is down; it restarts within seconds

    def wait_progress(self, min_s: float, max_s: float, timeout: float = 90.0) -> Counter:
        """Until a random dwell in [min_s, max_s] has passed and some request was added or finished."""
        c0 = request_counts(self.args.data)
        if not self.work_left(c0):
            return c0
        dwell, start = self.rng.uniform(min_s, max_s), time.monotonic()
        while True:
            time.sleep(0.2)
            c = request_counts(self.args.data)
            moved = (c["done"], sum(c.values())) != (c0["done"], sum(c0.values()))
            if moved and time.monotonic() - start >= dwell:
                return c
            if time.monotonic() - start > timeout:
                log(f"no progress in {timeout:g} s: {dict(c)}")
                return c

    def wait_file(self, trigger: str, timeout: float = 30.0) -> str | None:
        """Polls episodes/ every ~2 ms for a new staging file (``tmp``) or a new ``.mcap`` (``mcap*``)."""
        seen = episode_names(self.args.data)
        stale = {n for n in seen if n.endswith(".tmp")}  # leftovers of earlier kills
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            now = episode_names(self.args.data)
            suffix = ".tmp" if trigger == "tmp" else ".mcap"
            fresh = [n for n in now - (stale if trigger == "tmp" else seen) if n.endswith(suffix)]
            if fresh:
                return fresh[0]
            seen = now
            time.sleep(0.002)
        return None

    def kill_worker(self) -> None:
        c = self.wait_progress(1.0, 6.0)
        wid = str(self.rng.choice(self.cluster.worker_ids))
        self.cluster.kill(self.cluster.workers[wid], f"worker {wid}")
        self.events.append(f"kill worker {wid} at {dict(c)}")
        time.sleep(self.rng.uniform(0, 3))
        self.cluster.start_worker(wid)

    def kill_service(self, k: int, trigger: str) -> bool:
        """Kill #k of the service, then restart it; False when no work was left to interrupt."""
        c = self.wait_progress(1.0, 6.0)
        if not self.work_left(c):
            self.events.append(f"kill #{k} skipped: no work left")
            log(f"no work left; kill #{k} skipped")
            return False
        hit = self.wait_file(trigger) if trigger != "random" else None
        self.cluster.kill(self.cluster.service, f"service #{self.cluster.service_starts} ({trigger})")
        if trigger == "mcap-all":
            for wid in self.cluster.worker_ids:
                self.cluster.kill(self.cluster.workers[wid], f"worker {wid}")
            for wid in self.cluster.worker_ids:
                self.cluster.start_worker(wid)
        self.events.append(f"kill service #{k} ({trigger}{': ' + hit if hit else ''}) at {dict(c)}")
        time.sleep(self.rng.uniform(0, 2.0))
        self.cluster.start_service()
        return True

    def run(self) -> None:
        a = self.args
        self.cluster.start_service()
        for wid in self.cluster.worker_ids:
            self.cluster.start_worker(wid)
        keys = [(f"chaos-{a.seed}-{i}", 1000 + i) for i in range(a.requests)]
        threads = [threading.Thread(target=self.enqueue, args=(keys[j::2],), daemon=True) for j in range(2)]
        for t in threads:
            t.start()
        n_worker_kills = min(a.worker_kills, max(a.kills - 1, 0))
        worker_kill_before = set(self.rng.choice(np.arange(1, a.kills), n_worker_kills, replace=False).tolist()) \
            if n_worker_kills else set()
        for k in range(1, a.kills + 1):
            if k in worker_kill_before:
                self.kill_worker()
            if not self.kill_service(k, a.triggers[(k - 1) % len(a.triggers)]):
                break
        for t in threads:
            t.join()
        log(f"all {len(self.acked)} enqueues acknowledged ({self.enqueue_retries} retries)")
        self.drain(a.drain_timeout)
        self.cluster.stop()

    def drain(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            c = request_counts(self.args.data)
            if c["queued"] + c["leased"] == 0 and sum(c.values()) >= self.args.requests:
                break
            time.sleep(0.5)
        log(f"drained: {dict(request_counts(self.args.data))}")


def read_rows(data: Path) -> tuple[dict[str, dict], list[dict]]:
    """Every request (by id) and every episode row of the catalog, once the processes have stopped."""
    con = sqlite3.connect(data / DB_NAME)
    con.row_factory = sqlite3.Row
    try:
        return ({r["id"]: dict(r) for r in con.execute("SELECT * FROM requests")},
                [dict(r) for r in con.execute("SELECT * FROM episodes")])
    finally:
        con.close()


def check_requests(reqs: dict[str, dict], eps: list[dict], acked: dict[str, str], n: int) -> list[str]:
    """Invariants 1-3 (catalog rows against the acknowledgements)."""
    problems = []
    acked_ids = set(acked.values())
    if len(acked) != n:
        problems.append(f"only {len(acked)} of {n} enqueues acknowledged")
    if missing := acked_ids - set(reqs):
        problems.append(f"{len(missing)} acknowledged requests missing from the catalog: {sorted(missing)[:3]}")
    if extra := set(reqs) - acked_ids:
        problems.append(f"{len(extra)} requests in the catalog never acknowledged: {sorted(extra)[:3]}")
    keys = [r["idempotency_key"] for r in reqs.values()]
    if len(keys) != len(set(keys)):
        problems.append("duplicate idempotency keys")
    for status in ("queued", "leased"):
        if stuck := sum(r["status"] == status for r in reqs.values()):
            problems.append(f"{stuck} requests still {status}")
    return problems + check_episode_rows(reqs, eps)


def check_episode_rows(reqs: dict[str, dict], eps: list[dict]) -> list[str]:
    """Invariant 3: a done request has exactly the one episode it names, any other request none, and every
    train episode names a done request."""
    problems = []
    by_req: dict[str, list[dict]] = {}
    for e in eps:
        by_req.setdefault(e["request_id"], []).append(e)
    for rid, r in reqs.items():
        mine = by_req.get(rid, [])
        if r["status"] == "done" and [e["episode_id"] for e in mine] != [r["episode_id"]]:
            problems.append(f"done request {rid} names episode {r['episode_id']}, the catalog has "
                            f"{[e['episode_id'] for e in mine]}")
        elif r["status"] != "done" and mine:
            problems.append(f"{r['status']} request {rid} has {len(mine)} episodes")
    for e in eps:
        r = reqs.get(e["request_id"])
        if e["split"] == "train" and (r is None or r["status"] != "done"):
            problems.append(f"train episode {e['episode_id']} names request {e['request_id']} "
                            f"which is {r and r['status']}")
    return problems


def check_files(data: Path, eps: list[dict]) -> tuple[list[str], list[str]]:
    """Invariants 4-5 (files on disk); returns (problems, notes)."""
    problems, notes = [], []
    for e in eps:
        p = data / e["path"]
        if not p.is_file():
            problems.append(f"episode {e['episode_id']} file missing: {e['path']}")
        elif hashlib.sha256(p.read_bytes()).hexdigest() != e["sha256"]:
            problems.append(f"episode {e['episode_id']} sha256 mismatch")
    indexed = {e["path"] for e in eps}
    episodes = data / "episodes"
    unindexed = [p.relative_to(data).as_posix() for p in episodes.rglob("*.mcap")
                 if not p.name.startswith(".") and p.relative_to(data).as_posix() not in indexed]
    if unindexed:
        problems.append(f"{len(unindexed)} unindexed .mcap files under episodes/: {unindexed[:3]}")
    now = time.time()
    staging = list(episodes.rglob("*.tmp"))
    old = [p.relative_to(data).as_posix() for p in staging if now - p.stat().st_mtime > STAGING_MAX_AGE_S]
    if old:
        problems.append(f"{len(old)} staging files older than {STAGING_MAX_AGE_S:g} s: {old[:3]}")
    if young := len(staging) - len(old):
        notes.append(f"{young} staging files younger than {STAGING_MAX_AGE_S:g} s (a later sweep deletes them)")
    elsewhere = [p.relative_to(data).as_posix() for p in data.rglob("*.tmp")
                 if episodes not in p.parents and data / LOGS not in p.parents]
    if elsewhere:
        problems.append(f"tmp files outside episodes/: {elsewhere[:3]}")
    r = subprocess.run([ACTIVECOLLECT, "episodes", "verify", "--data", str(data), "--json"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        problems.append(f"episodes verify exited {r.returncode}: {r.stdout[:300]} {r.stderr[-300:]}")
    return problems, notes


def summarize(chaos: Chaos) -> dict:
    """Checks every invariant and gathers the counts of the run."""
    a, data = chaos.args, chaos.args.data
    reqs, eps = read_rows(data)
    problems = check_requests(reqs, eps, chaos.acked, a.requests)
    file_problems, notes = check_files(data, eps)
    logs = chaos.cluster.logs
    wlogs = "".join(p.read_text(errors="replace") for p in logs.glob("worker.*.log"))
    slogs = "".join(p.read_text(errors="replace") for p in logs.glob("service.*.log"))
    orphans = data / ORPHANS_DIR
    return {
        "seed": a.seed, "requests": a.requests, "by_status": dict(Counter(r["status"] for r in reqs.values())),
        "episodes": len(eps), "orphans_moved": sum(1 for p in orphans.rglob("*") if p.is_file()),
        "service_kills": sum(e.startswith("kill service") for e in chaos.events),
        "worker_kills": sum(e.startswith("kill worker") for e in chaos.events),
        "service_starts": chaos.cluster.service_starts, "worker_starts": dict(chaos.cluster.worker_starts),
        "enqueue_retries": chaos.enqueue_retries,
        "leased_more_than_once": sum((r["token"] or 0) > 1 for r in reqs.values()),
        "attempts": dict(sorted(Counter(r["attempts"] for r in reqs.values()).items())),
        "dead": [(r["id"][:8], r["attempts"], r["last_error"]) for r in reqs.values() if r["status"] == "dead"],
        "worker_upload_retries": wlogs.count("upload: "), "worker_duplicate_acks": wlogs.count("(duplicate)"),
        "worker_dropped_episodes": wlogs.count("dropping the episode"),
        "worker_stale_refusals": wlogs.count("no longer ours"),
        "service_leases_expired": slogs.count("expired (attempt"),
        "elapsed_s": round(time.monotonic() - T0, 1),
        "problems": problems + file_problems, "notes": notes, "events": chaos.events,
    }


def exit_on_sigterm(signum: int, frame: object) -> None:
    """SIGTERM (a supervisor, ``timeout``) unwinds as Ctrl-C does, through the ``finally`` that kills the service
    and the workers: they run in sessions of their own, so nothing else would stop them."""
    sys.exit(128 + signum)


def main(argv=None) -> int:
    p = Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, metavar="DIR",
                   help="new or empty directory: the service's data directory (process logs in DATA/chaos-logs/)")
    p.add_argument("--requests", type=int, default=150, metavar="N", help="requests to enqueue (default 150)")
    p.add_argument("--kills", type=int, default=9, metavar="N", help="service SIGKILLs (default 9)")
    p.add_argument("--worker-kills", type=int, default=2, metavar="N",
                   help="worker SIGKILLs, each just before a service kill (default 2; at most --kills - 1)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="seeds kill timings and targets (default random)")
    p.add_argument("--steps", type=int, default=20, metavar="N", help="simulation steps per request (default 20)")
    p.add_argument("--upload-part-kb", type=flags.positive_int, default=None, metavar="KB",
                   help="workers' --upload-part-kb (default theirs): small parts put service kills mid-upload "
                        "between the parts")
    p.add_argument("--realtime", type=flags.realtime, default=0.5, metavar="X",
                   help="workers' --realtime: an episode takes X * steps / 10 s (default 0.5; 0 = flat out)")
    p.add_argument("--triggers", default="random,tmp,mcap", metavar="LIST",
                   help=f"comma list cycled over the service kills, of {', '.join(TRIGGERS)} (default random,tmp,mcap)")
    p.add_argument("--drain-timeout", type=float, default=300.0, metavar="S",
                   help="seconds to wait for the queue to empty (default 300)")
    p.add_argument("--json", type=Path, metavar="FILE", help="also write the summary here")
    a = p.parse_args(argv)
    a.triggers = a.triggers.split(",")
    if bad := set(a.triggers) - set(TRIGGERS):
        p.error(f"unknown triggers {sorted(bad)}; expected some of {', '.join(TRIGGERS)}")
    if a.data.exists() and (not a.data.is_dir() or any(a.data.iterdir())):
        print(f"chaos: {a.data} is not an empty directory; give a new or empty one", file=sys.stderr)
        return 2
    if a.seed is None:
        a.seed = int(np.random.SeedSequence().entropy % (1 << 30))
    log(f"data {a.data}, seed {a.seed}")
    chaos = Chaos(a)
    signal.signal(signal.SIGTERM, exit_on_sigterm)  # the service and workers are in sessions of their own
    try:
        chaos.run()
    finally:
        chaos.cluster.kill_all()
    summary = summarize(chaos)
    text = json.dumps(summary, indent=1, default=str)
    print(text)
    if a.json:
        a.json.write_text(text)
    s = summary
    log(f"seed {a.seed}: {s['requests']} requests {s['by_status']}, {s['episodes']} episodes, "
        f"{s['service_kills']} service and {s['worker_kills']} worker kills, {s['orphans_moved']} orphans moved, "
        f"{s['elapsed_s']} s: INVARIANTS " + ("HOLD" if not s["problems"] else f"VIOLATED ({len(s['problems'])})"))
    return 1 if s["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
