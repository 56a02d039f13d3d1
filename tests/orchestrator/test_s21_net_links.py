"""A router killed and restarted under a connected service and worker: Zenoh reconnects them by itself, and each
says so (before, nothing was said; the service only logged its workers as lost)."""

from __future__ import annotations

import signal
import sys

import pytest

from tests.conftest import free_port
from tests.orchestrator.test_router import start_plain_router
from tests.orchestrator.test_secure import Proc


def client_process(name: str, endpoint: str, tmp_path) -> Proc:
    """``serve`` or a worker agent connected to ``endpoint`` as a Zenoh client, once it is up."""
    if name == "serve":
        argv = ["-m", "orchestrator", "serve", "--data", str(tmp_path / "data"), "--init", "--planner", "none",
                "--dashboard-port", str(free_port())]
        ready = "serving activecollect"
    else:
        argv = ["-m", "workers.agent", "--id", "w-links", "--timeout", "1"]
        ready = "worker w-links up"
    return Proc([sys.executable, *argv, "--mode", "client", "--connect", endpoint]).started(ready)


@pytest.mark.parametrize("name", ["serve", "worker"])
def test_a_router_restart_is_said_and_outlived(name, procs, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_plain_router((endpoint,))
    procs.append(router)
    proc = client_process(name, endpoint, tmp_path)
    procs.append(proc)
    router.popen.send_signal(signal.SIGKILL)
    router.popen.wait(15)
    proc.wait_line("lost the link to Zenoh router")
    assert proc.popen.poll() is None, proc.output()
    procs.append(start_plain_router((endpoint,)))
    back = proc.wait_line("linked to Zenoh router", timeout=60)
    assert "again after" in back and proc.popen.poll() is None, proc.output()
    assert proc.stop() == 0, proc.output()
