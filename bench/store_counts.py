"""What the service's once-a-second gauges (``ServiceMetrics.read_stores``: queue depth, episodes per split, ...)
cost as the history grows: finished requests and episode rows are never deleted, and the counts read them.

Builds a catalog with one real episode (the simulator's, recorded and ingested), then copies its row and its
done request --rows times by SQL (the counts read rows, not files), and times, in the same run, with each repeat
alternating the two: the catalog's count of one split (``Catalog.count(split="train")``, the index of the split
alone) against the same count joined with the quarantine (what it was before the twenty-ninth session: the join
read every row), and ``read_stores`` and ``RequestQueue.counts`` as they are.

Usage: .venv/bin/python bench/store_counts.py [--rows 200000] [--repeats 20] [--json OUT]
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
from storage import episode_table  # noqa: E402
from storage.catalog import Catalog  # noqa: E402
from storage.models import ModelRegistry  # noqa: E402
from storage.queue import RequestQueue  # noqa: E402
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


def run(rows: int, repeats: int, tmp: Path) -> dict:
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
    joined = f"SELECT COUNT(*) FROM {episode_table.FROM_ROWS} WHERE split = ?"

    def count_joined() -> int:
        with sqlite3.connect(catalog.db_path) as conn:
            return conn.execute(joined, ("train",)).fetchone()[0]

    assert count_joined() == catalog.count(split="train") == rows + 1
    metrics, registry = ServiceMetrics(), ModelRegistry(tmp / "data")
    figures = {"count_split_ms": [], "count_split_joined_ms": []}
    for _ in range(repeats):  # alternating, so that load on the machine falls on both alike
        figures["count_split_ms"].append(_ms(lambda: catalog.count(split="train"), 1))
        figures["count_split_joined_ms"].append(_ms(count_joined, 1))
    out = {k: statistics.median(v) for k, v in figures.items()}
    out.update(rows=rows, repeats=repeats, read_stores_ms=_ms(lambda: metrics.read_stores(queue, catalog, registry),
                                                               repeats),
               queue_counts_ms=_ms(queue.counts, repeats))
    out["joined_over_split"] = out["count_split_joined_ms"] / out["count_split_ms"]
    queue.close()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=200_000, help="episode rows and done requests (default 200000)")
    p.add_argument("--repeats", type=int, default=20, help="timed calls of each (default 20)")
    p.add_argument("--json", type=Path, help="write the figures there too")
    args = p.parse_args(argv)
    if args.rows < 0 or args.repeats < 1:
        p.error("--rows must be at least 0 and --repeats at least 1")
    with tempfile.TemporaryDirectory() as tmp:
        return emit(run(args.rows, args.repeats, Path(tmp)), args.json)


if __name__ == "__main__":
    sys.exit(main())
