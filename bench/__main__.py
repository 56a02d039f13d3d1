"""Run every benchmark in turn and save the JSON results (``make bench``).

Each benchmark measures its figure next to a baseline taken in the same run
(a ratio), because the machines are shared and noisy. Results are written to
``bench/results/<UTC timestamp>.json`` and printed; copy the figures, the
command, the machine and the date into BENCHMARKS.md. ``bench loop`` also
leaves its run (each seed's arms, config.json, summary.json, loop.png) in
``./activecollect-bench/loop-<local time>/`` under the directory make bench
runs in (its default --out; ``bench loop-summary`` reads it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import signal
import subprocess
import sys
from pathlib import Path

from orchestrator.cli.common import Parser
from orchestrator.signals import Terminated, sigterm_raises

HERE = Path(__file__).resolve().parent
PY = sys.executable
CLI = [PY, "-m", "orchestrator"]

BENCHES: dict[str, list[str]] = {
    "sim": [PY, str(HERE / "sim_vs_pusht.py"), "--seconds", "5", "--rounds", "3"],
    "score": CLI + ["bench", "score", "--json"],
    "dispatch": CLI + ["bench", "dispatch", "--workers", "8", "--json"],
    "loop": CLI + ["bench", "loop", "--seeds", "3", "--json"],
}


def _last_json(text: str) -> object:
    """The last JSON object or list in the output that starts a line, compact or indented over many lines
    (benchmarks may log before it); an error record when there is none."""
    decoder = json.JSONDecoder()
    starts = [0]
    for line in text.splitlines(keepends=True):
        starts.append(starts[-1] + len(line))
    for start in reversed(starts[:-1]):  # a nested line of an indented document starts with a space
        if text.startswith(("{", "["), start):
            try:
                return decoder.raw_decode(text, start)[0]
            except json.JSONDecodeError:
                continue
    return {"error": "no JSON in output", "tail": text[-2000:]}


def _run(cmd: list[str]) -> tuple[int, str, str, int | None]:
    """(exit status, stdout, stderr, the signal that stopped this run or None). A Ctrl-C reached the benchmark too
    (the terminal sends it to the whole process group), a SIGTERM is passed on to it; either way the benchmark is
    left to stop as it does alone (``bench loop`` summarises the rounds it finished, ``bench dispatch`` stops its
    servers and removes its temporary directory) before it is killed."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate()
        return proc.returncode, out, err, None
    except (KeyboardInterrupt, Terminated) as exc:
        stopped = signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT
        if stopped == signal.SIGTERM:
            proc.terminate()
        try:
            out, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        return proc.returncode, out, err, stopped


def main(argv: list[str] | None = None) -> int:
    parser = Parser(prog="python -m bench", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", default=",".join(BENCHES),
                        help=f"comma-separated subset of {','.join(BENCHES)} (default: all)")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.only.split(",") if n.strip()]
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; choose from {list(BENCHES)}")
    if not names:  # (an unset $ONLY: nothing would run, and an empty results file would say it passed)
        parser.error(f"--only names no benchmark, found {args.only!r}; choose from {list(BENCHES)}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # (the second run's figures would replace the first's in the results file)
        parser.error(f"--only names {', '.join(twice)} twice; a benchmark runs once per run")
    started = dt.datetime.now(dt.timezone.utc)
    results: dict[str, object] = {
        "started": started.isoformat(timespec="seconds"),
        "machine": {"node": platform.node(), "cpu_count": __import__("os").cpu_count(),
                    "python": platform.python_version(), "platform": platform.platform()},
    }
    failed = []
    stopped = None
    with sigterm_raises():  # SIGTERM raises Terminated here, as Ctrl-C raises KeyboardInterrupt (see _run)
        for name in names:
            print(f"== bench {name}: {' '.join(BENCHES[name])}", file=sys.stderr, flush=True)
            returncode, out, err, stopped = _run(BENCHES[name])
            results[name] = _last_json(out)
            if returncode != 0:
                failed.append(name)
                results[name] = {"error": f"exit {returncode}", "stderr": err[-2000:], "output": results[name]}
            print(json.dumps(results[name], indent=2, default=str))
            if stopped is not None:
                results["interrupted"] = {"by": stopped.name, "during": name}
                break
        out_dir = HERE / "results"
        out_dir.mkdir(exist_ok=True)
        out = out_dir / f"{started:%Y%m%dT%H%M%SZ}.json"
        out.write_text(json.dumps(results, indent=2, default=str))
        print(f"results written to {out}", file=sys.stderr)
        if stopped is not None:
            return 128 + stopped
        return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
