"""The lock that keeps a second service off a data directory one already serves, and what its file says.

SQLite serves one orchestrator (DESIGN.md): two services on one catalog would run two planners, two lease
reapers, two sweeps of strays (one moving aside a file the other is staging) and two retrain schedulers.
``ServiceLock`` holds ``DATA/service.lock`` (``fcntl.flock``, as the retrain lock does: the kernel drops it when
the holder dies, SIGKILL included, so a restart right after a crash starts) from before the service writes
anything until it stops; the file names the holder (pid, start time, where it is reached), which the refusal
a second service gets quotes. The descriptor is close-on-exec: a retrain job or a worker the service started
never holds the directory once the service is gone. Offline commands (``ingest``, ``collect``, ``retrain``,
``backup`` ...) do not take it: they write beside a running service by design.
"""

from __future__ import annotations

import fcntl
import json
import os
import time
from pathlib import Path

from storage.errors import StorageError

LOCK_NAME = "service.lock"
#: How long a refused start waits for a holder that has just taken the lock to write its name into the file.
NAMED_WITHIN_S = 1.0


class DataDirectoryBusyError(StorageError):
    """Another service (another process, or another ``ServiceLock`` in this one) holds the data directory."""


class ServiceLock:
    """``DATA/service.lock``, held by one service from ``acquire()`` to ``release()``."""

    def __init__(self, data_dir: Path) -> None:
        self.path = Path(data_dir) / LOCK_NAME
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        """Whether this lock object holds the directory now."""
        return self._fd is not None

    def acquire(self, where: str = "", namespace: str = "") -> None:
        """Take the lock without waiting, then write the holder's pid, start time, ``where`` it is reached and
        its ``namespace`` into the file. A no-op when this object holds it already.

        Raises DataDirectoryBusyError naming the holder when another holds it; OSError when the file cannot
        be made, opened or written (the lock is not kept then).
        """
        if self._fd is not None:
            return
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)  # (O_CLOEXEC: Python's default too)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise DataDirectoryBusyError(busy_message(self.path, wait_for_holder(self.path))) from None
            write_holder(fd, {"pid": os.getpid(), "started": time.time(), "where": where, "namespace": namespace})
        except BaseException:
            os.close(fd)  # (closing releases the flock)
            raise
        self._fd = fd

    def release(self) -> None:
        """Let the directory go (the file stays, naming its last holder: read it only while it is held).
        Idempotent."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def write_holder(fd: int, info: dict) -> None:
    """Replace what the lock file open at ``fd`` says about its holder with ``info`` (JSON); also the retrain lock's."""
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)


def read_holder(path: Path) -> dict:
    """What the lock file at ``path`` says about its holder ({} when empty, unreadable or not ours); also the
    retrain lock's."""
    try:
        info = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):  # (ValueError: a half-written file, or one that is not JSON or UTF-8)
        return {}
    return info if isinstance(info, dict) else {}


def wait_for_holder(path: Path, within_s: float = NAMED_WITHIN_S) -> dict:
    """``read_holder``, waiting up to ``within_s`` for a holder that has just taken the lock to name itself."""
    deadline = time.monotonic() + within_s
    while not (info := read_holder(path)).get("pid") and time.monotonic() < deadline:
        time.sleep(0.02)
    return info


def busy_message(path: Path, holder: dict) -> str:
    """The one line a second service is refused with: who holds ``path``, as far as its file says."""
    about = [f"pid {holder.get('pid', 'unknown')}"]
    started = holder.get("started")
    if type(started) in (int, float) and 0 < started < 1e11:  # (a time this file could hold, not bool or nan)
        about.append(f"started {time.strftime('%Y-%m-%d %H:%M:%S %z', time.localtime(started))}")
    about += [str(holder["where"])] if holder.get("where") else []
    about += [f"namespace {holder['namespace']}"] if holder.get("namespace") else []
    return f"another service holds {path} ({', '.join(about)}): one service per data directory; not starting"
