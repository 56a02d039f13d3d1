"""What the service's once-a-second gauges (``ServiceMetrics.read_stores``: queue depth, episodes per split, ...)
cost as the history grows -- finished requests and episode rows are never deleted -- and what keeping the counts
costs the writes.

Builds a catalog with one real episode (the simulator's, recorded and ingested), then copies its row and its
done request --rows times by SQL (the counts read rows, not files), and times, in the same run, with each repeat
alternating the two: the counts the triggers keep (``Catalog.count(split="train")``, ``RequestQueue.counts``:
a few rows of ``episode_counts`` / ``request_counts``) against the same counted from the rows (what they did
before the thirtieth session: a split's index, each status's partial index), and ``read_stores`` as it is.
Then the cost to the writes: lease-and-complete cycles (what each episode does to the queue: the complete fires a
trigger) and lease-and-release cycles (no trigger fires: leases, renewals and fails move only live statuses,
which are not kept) on a queue with the triggers against one whose triggers were dropped, alternating in batches.

Usage: .venv/bin/python bench/store_counts.py [--rows 200000] [--repeats 20] [--cycles 2000] [--json OUT]
"""

from __future__ import annotations

import argparse
import sqlite3
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Callable

import numpy as np
from jsonout import emit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from orchestrator.metrics import ServiceMetrics  # noqa: E402 (the repository on the path first)
from storage.catalog import Catalog  # noqa: E402
from storage.models import ModelRegistry  # noqa: E402
from storage.queue import RequestQueue  # noqa: E402
from storage.request_table import RECOUNT_SQL  # noqa: E402
from storage.requests import NewRequest  # noqa: E402
from workers.collect import collect_episode  # noqa: E402
from workers.env import sample_state  # noqa: E402


def _ms(fn: Callable[[], object], repeats: int) -> float:
    """Median milliseconds of ``fn()`` over ``repeats`` calls, after one to warm the page cache."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1000)
    return statistics.median(times)


def _copies(conn: sqlite3.Connection, rows: int) -> None:
    """``rows`` copies of the one episode row and its done request, under new ids."""
    ep_cols = [r[1] for r in conn.execute("PRAGMA table_info(episodes)")]
    rq_cols = [r[1] for r in conn.execute("PRAGMA table_info(requests)")]
    ep = dict(zip(ep_cols, conn.execute("SELECT * FROM episodes WHERE split = 'train' LIMIT 1").fetchone()))
    rq = dict(zip(rq_cols, conn.execute("SELECT * FROM requests LIMIT 1").fetchone()))
    conn.execute("BEGIN")
    for i in range(rows):
        rid = uuid.uuid4().hex
        conn.execute(f"INSERT INTO requests ({','.join(rq)}) VALUES ({','.join('?' * len(rq))})",
                     list({**rq, "id": rid, "idempotency_key": None, "episode_id": f"copy{i}"}.values()))
        conn.execute(f"INSERT INTO episodes ({','.join(ep)}) VALUES ({','.join('?' * len(ep))})",
                     list({**ep, "episode_id": f"copy{i}", "request_id": rid, "path": f"episodes/c/{i}.mcap"}.values()))
    conn.execute("COMMIT")


def _cycles(queue: RequestQueue, n: int, finish: bool) -> float:
    """Seconds for ``n`` lease-and-complete cycles (``finish``: each request done, the counted transition) or
    lease-and-release cycles (the request back in the queue: live statuses only) on requests enqueued before."""
    queue.enqueue_many([NewRequest(task="push", shape="T", start_state={}, steps=5) for _ in range(n)])
    start = time.perf_counter()
    for i in range(n):
        lease = queue.lease("bench")
        if finish:
            queue.complete(lease.request.id, lease.token, f"cycle{i}")
        else:
            queue.release(lease.request.id, lease.token)
    return time.perf_counter() - start


def write_cost(cycles: int, tmp: Path) -> dict:
    """Cycles per second with the count triggers and without them, alternating batches: lease-and-complete (each
    fires one) and lease-and-release (none fires: the live statuses are not kept)."""
    kept, bare = RequestQueue(tmp / "kept.sqlite"), RequestQueue(tmp / "bare.sqlite")
    with sqlite3.connect(bare.db_path) as conn:  # the queue, already open, writes on without them
        for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'trigger'").fetchall():
            conn.execute(f"DROP TRIGGER {name}")
    batch = max(1, cycles // 10)
    rounds = max(1, cycles // batch)
    out: dict = {"cycles": batch * rounds}
    for finish, name in ((True, "complete"), (False, "release")):
        seconds = {"kept": 0.0, "bare": 0.0}
        for i in range(rounds):  # each first in every other round
            for which, queue in ((("kept", kept), ("bare", bare)) if i % 2 else (("bare", bare), ("kept", kept))):
                seconds[which] += _cycles(queue, batch, finish)
        out.update({f"{name}_per_s_kept": out["cycles"] / seconds["kept"],
                    f"{name}_per_s_bare": out["cycles"] / seconds["bare"],
                    f"{name}_cost_ratio": seconds["kept"] / seconds["bare"]})
    assert kept.counts()["done"] == out["cycles"]  # the triggers counted every one of them
    kept.close()
    bare.close()
    return out


def run(rows: int, repeats: int, cycles: int, tmp: Path) -> dict:
    catalog = Catalog(tmp / "data")
    queue = RequestQueue(catalog.db_path)
    request, _ = queue.enqueue(NewRequest(task="push", shape="T", start_state={}, steps=5))
    lease = queue.lease("bench")
    episode = collect_episode(start_state=sample_state(np.random.default_rng(0), shape="T").to_dict(), policy="push",
                              seed=0, steps=5, image_size=16, request_id=request.id)
    stored = catalog.add_episode(episode)
    queue.complete(request.id, lease.token, stored.episode_id)
    with sqlite3.connect(catalog.db_path, isolation_level=None) as conn:
        _copies(conn, rows)
    # One connection, kept (as the queue keeps its own): the counts from the rows do not pay for opening one,
    # which the catalog's count does (0.2 ms of it)
    rows_conn = sqlite3.connect(catalog.db_path)

    def recount_split() -> int:
        return rows_conn.execute("SELECT COUNT(*) FROM episodes WHERE split = ?", ("train",)).fetchone()[0]

    def recount_queue() -> dict[str, int]:
        return {s: n for s, n in rows_conn.execute(RECOUNT_SQL) if n}

    assert recount_split() == catalog.count(split="train") == rows + 1
    assert recount_queue() == {s: n for s, n in queue.counts().items() if n} == {"done": rows + 1}
    metrics, registry = ServiceMetrics(), ModelRegistry(tmp / "data")
    figures: dict[str, list[float]] = {"count_split_ms": [], "count_split_rows_ms": [], "queue_counts_ms": [],
                                       "queue_counts_rows_ms": []}
    for _ in range(repeats):  # alternating, so that load on the machine falls on both alike
        figures["count_split_ms"].append(_ms(lambda: catalog.count(split="train"), 1))
        figures["count_split_rows_ms"].append(_ms(recount_split, 1))
        figures["queue_counts_ms"].append(_ms(queue.counts, 1))
        figures["queue_counts_rows_ms"].append(_ms(recount_queue, 1))
    out: dict = {k: statistics.median(v) for k, v in figures.items()}
    out.update(rows=rows, repeats=repeats, read_stores_ms=_ms(lambda: metrics.read_stores(queue, catalog, registry),
                                                               repeats))
    out["split_rows_over_kept"] = out["count_split_rows_ms"] / out["count_split_ms"]
    out["queue_rows_over_kept"] = out["queue_counts_rows_ms"] / out["queue_counts_ms"]
    queue.close()
    rows_conn.close()
    out.update(write_cost(cycles, tmp))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=200_000, help="episode rows and done requests (default 200000)")
    p.add_argument("--repeats", type=int, default=20, help="timed calls of each (default 20)")
    p.add_argument("--cycles", type=int, default=2000,
                   help="lease-and-complete cycles timed with the triggers and without (default 2000)")
    p.add_argument("--json", type=Path, help="write the figures there too")
    args = p.parse_args(argv)
    if args.rows < 0 or args.repeats < 1 or args.cycles < 1:
        p.error("--rows must be at least 0, --repeats and --cycles at least 1")
    with tempfile.TemporaryDirectory() as tmp:
        return emit(run(args.rows, args.repeats, args.cycles, Path(tmp)), args.json)


if __name__ == "__main__":
    sys.exit(main())
