"""A retrain job as ``orchestrator.scheduler`` runs it: its schedule (``ScheduleConfig``), its record and status,
the command and process settings of the child, and how what it left (stdout, log, notes) is read.

No torch, no threads: the records and readers the scheduler, the loop, the dashboard and the CLI share.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import json
import signal
import sys
import time
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path

from croniter import CroniterBadDateError, croniter


class RetrainStatus(str, Enum):
    running = "running"
    promoted = "promoted"
    rejected = "rejected"
    failed = "failed"
    killed = "killed"
    timeout = "timeout"
    busy = "busy"


@dataclass
class ScheduleConfig:
    """When to retrain and how a job is run."""

    every_episodes: int = 0
    """Retrain each time the training episode count crosses a multiple of this (0 = never on count)."""
    cron: str = ""
    """Also retrain on this cron expression of 5 fields, e.g. ``*/10 * * * *``, read in UTC ('' = never on time)."""
    timeout_s: float = 4 * 3600.0
    """A job running longer than this is killed (changing nothing, unless its gate had already decided). A job
    trains on every training window unless its arguments bound them (``--max-windows``): its time grows with the
    catalog (retrain's defaults on 2 CPU cores: ~90 ms a window, so 30 minutes, the old default, was past at ~400
    episodes of 50 steps and every retrain then failed)."""
    poll_s: float = 0.5
    """How often the scheduler thread checks whether a job is due or done."""
    retrain_args: tuple[str, ...] = ()
    """Extra arguments given to ``activecollect retrain`` (training and gate settings)."""
    threads: int = 0
    """Torch threads of each job (``retrain --threads``, given before ``retrain_args``, so a ``--threads``
    there wins; 0 = torch's default, one per core)."""

    def __post_init__(self) -> None:
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, found {self.threads}")
        if self.every_episodes < 0:
            raise ValueError(f"every_episodes must be >= 0, found {self.every_episodes}")
        problem = cron_problem(self.cron) if self.cron else None
        if problem:
            raise ValueError(problem)
        if self.timeout_s <= 0 or self.poll_s <= 0:
            raise ValueError(f"timeout_s and poll_s must be > 0, found {self.timeout_s} and {self.poll_s}")


def cron_problem(expr: str) -> str | None:
    """Why ``expr`` cannot be a retrain schedule, or None when it can: a cron expression of 5 fields (minute hour
    day month weekday) or an @-name such as ``@hourly``, that fires. (croniter also reads a sixth field, seconds,
    and a seventh, the year: a schedule that retrains all through a minute, or once and never again.)"""
    if len(expr.split()) != (1 if expr.startswith("@") else 5) or not croniter.is_valid(expr):
        return (f"cron must be a cron expression of 5 fields (minute hour day month weekday) like '*/10 * * * *', "
                f"found {expr!r}")
    try:
        croniter(expr, time.time()).get_next(float)
    except CroniterBadDateError:
        return f"cron {expr!r} never fires: no date matches it"
    return None


@dataclass
class RetrainRecord:
    """One retrain job, as the dashboard and the report show it."""

    trigger: str
    """Why it ran: ``episodes``, ``cron``, ``manual`` or what ``request`` was given (``round``)."""
    started: float
    """Unix time the job started."""
    episodes: int
    """Training episodes in the catalog when it started."""
    status: RetrainStatus = RetrainStatus.running
    finished: float | None = None
    version: str = ""
    """The candidate's version ('' when it did not get that far)."""
    reason: str = ""
    """The gate's decision, or why the job failed."""
    metrics: dict = field(default_factory=dict)
    returncode: int | None = None
    log_path: str = ""
    job: str = ""
    """The id the job was given (``JOB_ENV``), by which its notes in the lock file are known."""

    def to_json(self) -> dict:
        d = asdict(self)
        d["status"] = self.status.value
        return d


def quarantined_note(episode_ids: list[str]) -> str:
    """One line for the operator on the train episodes a job found missing or damaged."""
    shown = ", ".join(episode_ids[:5]) + (f" and {len(episode_ids) - 5} more" if len(episode_ids) > 5 else "")
    return (f"quarantined {len(episode_ids)} train episode(s) whose files are missing or damaged: {shown} "
            "(trained without them; `activecollect episodes ls --quarantined` lists them, re-ingesting their "
            "bytes restores them)")


_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_prctl = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).prctl  # resolved before any fork


def die_with_parent() -> None:
    """``preexec_fn`` of a child process, or the first call of a spawned one: SIGTERM it when the thread
    that started it dies (Linux).

    The *thread*, not the process: start the child from a thread that outlives it. ``preexec_fn``
    runs between fork and exec, where a lock another thread held at the fork is never released;
    this one only calls ``prctl`` (resolved before any fork) through ctypes, which takes none. A
    child that calls it itself must then check that its parent is still the one that started it
    (it may have died before the call).
    """
    _prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def retrain_command(data_dir: Path, extra: tuple[str, ...] = ()) -> list[str]:
    """The child process that runs one retrain job."""
    return [sys.executable, "-m", "orchestrator", "retrain", "--data", str(data_dir), "--json", *extra]


def notes_path(rec: RetrainRecord) -> Path:
    """The file where the job of ``rec`` keeps its notes (``orchestrator.retrainlock.NOTES_ENV``)."""
    return Path(rec.log_path + ".notes")


def last_json(path: Path) -> dict:
    """The last line of a job's stdout that parses as a JSON object ({} when none)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return {}
    with contextlib.suppress(json.JSONDecodeError):
        whole = json.loads(text)
        if isinstance(whole, dict):
            return whole
    lines = text.splitlines()
    for line in reversed(lines):
        with contextlib.suppress(json.JSONDecodeError):
            obj = json.loads(line)
            if isinstance(obj, dict):
                return obj
    return {}


def log_tail(path: Path, n: int = 300) -> str:
    try:
        text = path.read_text(errors="replace").strip()
    except OSError:
        return "no log"
    lines = text.splitlines()
    return lines[-1][-n:] if lines else "no output"


def signal_name(number: int) -> str:
    """SIGTERM for 15; "signal 35" for a number with no name (real-time signals)."""
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"
