"""A Ctrl-C (SIGINT to the whole process group, as a terminal sends it) or a SIGTERM stops the benchmarks promptly
and leaves none of their processes behind: ``activecollect bench dispatch`` with its two server children, and
``python -m bench`` (``make bench``) with the benchmark it runs."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, alive, children, wait_for


def _session(sid: int) -> dict[int, str]:
    """The live processes of session ``sid`` (the spawn fixture starts each process in a session of its own)."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            found[int(stat.parent.name)] = cmdline.replace(b"\0", b" ").decode(errors="replace")
    return found


def _peak_mib(pid: int) -> float:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0.0
    return int(next(line for line in status.splitlines() if line.startswith("VmHWM")).split()[1]) / 1024


def _servers_up(pid: int) -> bool:
    return sum("orchestrator.dispatchbench" in cmd for cmd in _session(pid).values()) == 2


def test_ctrl_c_stops_bench_dispatch_and_its_servers_at_once(spawn, tmp_path):
    bench = spawn("bench", "bench", "dispatch", "--workers", "1", "--seconds", "120", "--data", str(tmp_path / "d"))
    wait_for(lambda: _servers_up(bench.pid) or not bench.alive(), timeout=60, message="the echo and service servers")
    assert bench.alive(), bench.log()[-3000:]
    os.killpg(bench.pid, signal.SIGINT)
    assert bench.wait(timeout=20) == 130, bench.log()[-3000:]
    wait_for(lambda: not _session(bench.pid), timeout=10, message="no process of the benchmark left")
    log = bench.log()
    assert "Traceback" not in log, log[-3000:]
    assert log.strip().endswith("activecollect: interrupted")


def test_sigterm_stops_bench_dispatch_and_its_servers_and_removes_its_temporary_directory(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, PYTHONPATH=str(REPO), TMPDIR=str(tmp))
    bench = subprocess.Popen([sys.executable, "-m", "orchestrator", "bench", "dispatch", "--workers", "1",
                              "--seconds", "120"], cwd=REPO, env=env, start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: _servers_up(bench.pid) or bench.poll() is not None, timeout=60,
                 message="the echo and service servers")
        assert [p.name for p in tmp.iterdir()][0].startswith("activecollect-dispatch-")
        bench.send_signal(signal.SIGTERM)
        _, err = bench.communicate(timeout=20)
        assert bench.returncode == 143, err[-3000:]
        assert err.strip().splitlines()[-1] == "activecollect: terminated"
        wait_for(lambda: not _session(bench.pid), timeout=20, message="no process of the benchmark left")
        assert list(tmp.iterdir()) == []
    finally:
        if bench.poll() is None:
            bench.kill()
            bench.wait()


@pytest.mark.parametrize("sig, said", [(signal.SIGINT, "interrupted"), (signal.SIGTERM, "terminated")])
def test_ctrl_c_or_sigterm_of_make_bench_leaves_no_benchmark_running_and_keeps_the_results(spawn, sig, said):
    """Ctrl-C reaches the whole group; a SIGTERM (a supervisor's) the runner alone, which passes it on."""
    runner = spawn("make-bench", "--only", "dispatch", module="bench")
    wait_for(lambda: _servers_up(runner.pid) or not runner.alive(), timeout=60,
             message="the dispatch benchmark's servers")
    assert runner.alive(), runner.log()[-3000:]
    (bench_pid,) = children(runner.pid)
    if sig == signal.SIGINT:
        os.killpg(runner.pid, sig)
    else:
        os.kill(runner.pid, sig)
    assert runner.wait(timeout=30) == 128 + sig, runner.log()[-3000:]
    wait_for(lambda: not _session(runner.pid), timeout=10, message="no process of the benchmark left")
    written = re.search(r"results written to (\S+)", runner.log())
    assert written, runner.log()[-3000:]
    path = Path(written.group(1))
    try:
        results = json.loads(path.read_text())
    finally:
        path.unlink()
    assert path.parent == REPO / "bench" / "results"
    assert results["interrupted"] == {"by": sig.name, "during": "dispatch"}
    assert results["dispatch"]["error"] == f"exit {128 + sig}"
    assert said in results["dispatch"]["stderr"] and "Traceback" not in runner.log()
    assert bench_pid not in _session(runner.pid)


def test_ctrl_c_or_sigterm_stops_zenoh_cap_and_its_receiver(spawn):
    for sig, group in ((signal.SIGINT, True), (signal.SIGTERM, False)):
        # 70 MiB is over our cap: the capped receiver never answers, so the sender waits out --timeout
        cap = spawn("zenoh-cap", "--mb", "70", "--timeout", "120", module="bench.zenoh_cap")
        (receiver,) = wait_for(lambda: children(cap.pid) or not cap.alive(), timeout=60, message="the receiver")
        wait_for(lambda: _peak_mib(receiver) > 64 or not cap.alive(), timeout=60,
                 message="the oversized query reaching the receiver")
        assert cap.alive(), cap.log()[-3000:]
        (os.killpg if group else os.kill)(cap.pid, sig)
        cap.wait(timeout=20)
        wait_for(lambda: not _session(cap.pid), timeout=20, message=f"no process left after {sig.name}")


def test_sigterm_stops_chaos_with_its_service_and_workers(spawn, tmp_path):
    """The service and the workers run in sessions of their own (so that chaos can SIGKILL each alone): a SIGTERM
    that ended chaos outright left them running, reparented to init, collecting on."""
    chaos = spawn("chaos", "--data", str(tmp_path / "data"), "--requests", "60", "--kills", "3", "--worker-kills", "0",
                  "--steps", "20", "--realtime", "0.5", "--seed", "3", module="bench.chaos")

    def cluster() -> dict[int, str]:
        kids = children(chaos.pid)
        up = [cmd for cmd in kids.values() if "workers.agent" in cmd or " serve " in cmd]
        return {pid: cmd for pid, cmd in kids.items() if "workers.agent" in cmd or " serve " in cmd} \
            if len(up) == 4 or not chaos.alive() else {}

    started = wait_for(cluster, timeout=60, message="the service and three workers")
    assert chaos.alive(), chaos.log()[-3000:]
    chaos.signal(signal.SIGTERM)
    assert chaos.wait(timeout=30) == 143, chaos.log()[-3000:]
    wait_for(lambda: not any(alive(pid) for pid in started), timeout=20,
             message=f"the service and the workers gone: {sorted(started)}")
