"""How our long-running processes (``serve``, ``router``, ``worker``) are asked to stop.

SIGTERM, and SIGINT unless the process was started ignoring it. A shell starts a script's
background jobs with SIGINT ignored (a terminal's Ctrl-C is not theirs), an ignored signal stays
ignored across exec, and Python then installs no KeyboardInterrupt handler of its own; our
processes keep to the same, so a SIGINT their parent ignores does not stop them either (e.g. the
workers of an ``activecollect run`` started in a script's background). A supervisor stops them
with SIGTERM either way.

Imports nothing of ours: workers use it too.
"""

from __future__ import annotations

import signal
import threading
from typing import Callable


def on_stop_signals(handler: Callable[[], None]) -> Callable[[], None]:
    """Calls ``handler`` on SIGTERM and on SIGINT, unless SIGINT is ignored when this is called (as it is in
    a process started ignoring it, before anything of ours installs a handler): then it stays ignored.
    Returns a function that puts the previous handlers back. Outside the main thread, where Python takes
    no signal handlers, it installs nothing."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    sigs = [signal.SIGTERM] + ([signal.SIGINT] if signal.getsignal(signal.SIGINT) != signal.SIG_IGN else [])
    previous = {sig: signal.getsignal(sig) for sig in sigs}
    for sig in sigs:
        signal.signal(sig, lambda signum, frame: handler())

    def restore() -> None:
        for sig, old in previous.items():
            signal.signal(sig, old)
    return restore
