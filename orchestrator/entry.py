"""The ``activecollect`` command (and ``python -m orchestrator``): ``orchestrator.cli.main``, imported only after
``activecollect worker`` has taken the stop and drain signals (``workers.startup``).

The CLI's imports (torch, Zenoh, the simulator) take a second or two; until the worker's own handlers are in,
SIGUSR1 or SIGTERM would kill a just-started worker and SIGINT end it with a traceback. Guarded, such a signal
ends it cleanly, exit 0 (it holds no lease yet), as ``python -m workers.agent`` does. The other commands keep
Python's defaults (a Ctrl-C while they import is a KeyboardInterrupt, as ever).
"""

from __future__ import annotations

import sys


def main() -> int:
    if sys.argv[1:2] == ["worker"]:
        from workers import startup
        startup.guard()
    from orchestrator.cli import main as cli_main
    return cli_main()
