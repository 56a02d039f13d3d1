"""Processes that open a new, empty database at once (``collect`` making a catalog while a dashboard, ``stats`` or a
second command reads it): each makes it WAL, and SQLite answered all but one "database is locked" at once, without
the busy wait (a helper's reproduction: ``collect`` exit 1, about one run in fifteen with a reader polling)."""

from __future__ import annotations

import json
import subprocess
import sys

# Run in a fresh interpreter, which forks its openers while it has one thread (the test process may have more).
OPENERS = r"""
import json, multiprocessing, sys
from storage.database import connect

def opened(path, barrier, answers):
    try:
        barrier.wait(timeout=30)
        conn = connect(path)
        answers.put(conn.execute("PRAGMA journal_mode").fetchone()[0])
        conn.close()
    except Exception as exc:
        answers.put(f"{type(exc).__name__}: {exc}")

if __name__ == "__main__":
    ctx, n, folder = multiprocessing.get_context("fork"), 8, sys.argv[1]
    for trial in range(60):  # (the old code: a quarter of the trials had a "database is locked")
        barrier, answers = ctx.Barrier(n), ctx.Queue()
        procs = [ctx.Process(target=opened, args=(f"{folder}/catalog-{trial}.sqlite", barrier, answers))
                 for _ in range(n)]
        for p in procs:
            p.start()
        got = [answers.get(timeout=60) for _ in range(n)]
        for p in procs:
            p.join(timeout=60)
        if got != ["wal"] * n:
            print(json.dumps({"trial": trial, "got": got}))
            sys.exit(1)
    print(json.dumps({"trials": 60}))
"""


def test_processes_that_open_a_new_database_at_once_all_open_it_in_wal(tmp_path) -> None:
    script = tmp_path / "openers.py"
    script.write_text(OPENERS)
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and json.loads(proc.stdout) == {"trials": 60}, proc.stdout + proc.stderr[-2000:]
