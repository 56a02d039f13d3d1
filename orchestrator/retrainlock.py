"""The lock that keeps two retrains from training at once, and what its file says about the holder.

``retrain_lock`` holds ``DATA/retrain.lock`` (``fcntl.flock``: the kernel drops it when the holder dies, so a
killed job never leaves a stale lock) for one job; ``note_phase`` writes the holder's pid, phase, the model it
registered and (for a job the scheduler started) its job id into the file, which ``read_lock_info`` reads back:
for operators, and for ``orchestrator.scheduler``, which tells by it what a job that died before reporting did.
A job the scheduler started also keeps the same notes in a file of its own (``NOTES_ENV``; read as the lock file is):
the lock file's are the next holder's as soon as that one takes the lock, which it may do before the scheduler
has seen that the job ended.
Taken by the job itself (``orchestrator.retrain``), so a retrain started by system cron and one started by the
service's scheduler exclude each other too.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import time
from pathlib import Path
from typing import Iterator

from storage.servicelock import read_holder, write_holder

log = logging.getLogger(__name__)

LOCK_NAME = "retrain.lock"
#: The environment variable that names a scheduled job to itself; ``note_phase`` writes it into the lock file, so
#: that what a dead job left there is told from what an earlier holder with the same pid left.
JOB_ENV = "ACTIVECOLLECT_RETRAIN_JOB"
#: The environment variable that names a file of the job's own where ``note_phase`` writes its notes too, so that
#: the scheduler reads what a dead job left even when another retrain took the lock (and wrote its own notes in
#: the lock file) between the job's end and the scheduler's next look (``RetrainScheduler.poll_s``).
NOTES_ENV = "ACTIVECOLLECT_RETRAIN_NOTES"
#: Exit status of a retrain that found another one holding the lock.
EXIT_BUSY = 3


class SchedulerError(Exception):
    """The retrain schedule or a retrain job could not be set up."""


class RetrainBusyError(SchedulerError):
    """Another retrain holds the lock."""


@contextlib.contextmanager
def retrain_lock(data_dir: Path, wait: bool = False) -> Iterator[Path]:
    """Hold ``DATA/retrain.lock`` (``fcntl.flock``) for one retrain.

    The kernel drops the lock when the holder dies, so a killed job never leaves a
    stale lock. The file's content says who holds it and in which phase (see
    ``note_phase``). Raises ``RetrainBusyError`` when another process holds it and
    ``wait`` is False.
    """
    path = Path(data_dir) / LOCK_NAME
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            holder = read_lock_info(data_dir)
            raise RetrainBusyError(f"another retrain holds {path} (pid {holder.get('pid', '?')}, "
                                   f"phase {holder.get('phase', '?')}); not training") from None
        note_phase(data_dir, "locked", fd=fd, version="")  # a new holder: nothing registered yet
        try:
            yield path
        except BaseException:
            try:
                note_phase(data_dir, "failed", fd=fd)  # not "training" for good after a failed job
            except OSError:
                pass  # the job's own error is the one to report
            raise
    finally:
        os.close(fd)  # closing releases the flock


def note_phase(data_dir: Path, phase: str, fd: int | None = None, version: str | None = None) -> None:
    """Record the lock holder's pid and phase in the lock file (for operators, tests and the scheduler), and in
    the job's own notes file when the scheduler gave it one (``NOTES_ENV``).

    ``version``: the model the holder registered, kept through its later phases, so that a job that dies
    before reporting can be told by what it left (``RetrainScheduler``); None keeps the one this process
    noted since it took the lock.
    """
    if version is None:
        noted = read_lock_info(data_dir)
        version = noted.get("version", "") if noted.get("pid") == os.getpid() else ""
    job = os.environ.get(JOB_ENV, "")
    info = ({"pid": os.getpid(), "phase": phase, "time": time.time()}
            | ({"job": job} if job else {}) | ({"version": version} if version else {}))
    _keep_own_notes(info)  # first: a job killed between the two writes has its version in the file no one else writes
    own = fd is None
    if own:
        fd = os.open(Path(data_dir) / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        write_holder(fd, info)
    finally:
        if own:
            os.close(fd)


def _keep_own_notes(info: dict) -> None:
    """Replace the notes in the file ``NOTES_ENV`` names, if any, by ``info`` (a rename: whole or not at all)."""
    path = os.environ.get(NOTES_ENV, "")
    if not path:
        return
    tmp = f"{path}.tmp"
    try:
        Path(tmp).write_text(json.dumps(info))
        os.replace(tmp, path)
    except OSError as exc:  # the lock file has them (until the next holder): not worth failing the job over
        log.warning("cannot keep this job's notes in %s (the scheduler reads the lock file's instead): %s", path, exc)


def read_lock_info(data_dir: Path) -> dict:
    """What the lock file says about its holder ({} when empty or unreadable)."""
    return read_holder(Path(data_dir) / LOCK_NAME)


def lock_held(data_dir: Path) -> bool:
    """Whether some process holds the retrain lock right now."""
    path = Path(data_dir) / LOCK_NAME
    if not path.exists():
        return False
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False

