"""Scheduled retraining: when to retrain, and running each retrain in its own process.

``RetrainScheduler`` decides when a retrain is due (every N new training
episodes and/or on a cron expression), starts at most one job at a time as a
child process (``python -m orchestrator retrain --data DIR --json ...``), so
training never shares a GIL or a core budget with the request path, and reads
its one-line JSON result when it exits. When a job promotes a new champion,
``on_promoted(version)`` lets the service hot-swap its scorer and announce it.
A job that fails, times out or is killed before its gate leaves the champion as it was (a candidate it
registered is rejected as abandoned by the next job); one that
ends without reporting *after* it (a prune stalled past the timeout, a crash) has:
the model it registered, noted in its own notes file (and the lock file), is looked up in
the registry, so a promotion is still recorded and announced
(``RetrainScheduler._read_what_it_left``).

The lock that keeps two retrains from training at once is taken by the job
itself (``orchestrator.retrainlock``, held by ``orchestrator.retrain.run_retrain``), so it also
holds against ``activecollect retrain`` started by system cron or by hand.

The job's schedule, record and status, its command line and the readers of what it left are
``orchestrator.retrainjob``. This module imports no torch (the job does, in its own process), so
``serve`` and the CLI's parsers load it at no cost.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import secrets
import subprocess
import threading
import time
from pathlib import Path
from typing import Any, Callable

from croniter import croniter

from orchestrator.retrainjob import (RetrainRecord, RetrainStatus, ScheduleConfig, die_with_parent, last_json, log_tail,
                                     notes_path, quarantined_note, retrain_command, signal_name)
from orchestrator.retrainlock import EXIT_BUSY, JOB_ENV, NOTES_ENV, lock_held, read_lock_info
from storage.errors import StorageError
from storage.files import age_s, write_synced
from storage.models import ModelRegistry, ModelStatus
from storage.servicelock import read_holder

log = logging.getLogger(__name__)

#: Retrain records kept in ``RetrainScheduler.history`` (the dashboard's table, ``run``'s report): a service that
#: runs for months keeps the newest; every model stays in the registry (``models ls``).
HISTORY_KEPT = 500
#: Jobs whose logs (``logs/retrain-*.log`` and ``.log.out``) are kept: older ones are deleted as jobs finish.
LOGS_KEPT = 200
#: A step back of the wall clock (NTP, a host set right) larger than this reckons the next cron retrain from the
#: new time; after a smaller one the schedule waits for the times it already ran, as cron does (3 h).
CRON_STEP_BACK_S = 3 * 3600.0
#: Written (with the trigger and the job's notes file) when a scheduled job starts and removed when it ends, unless the
#: service's stop ended it before its gate: a job killed while it was still starting (before it took the retrain lock,
#: so its notes there are an earlier holder's) or between its register and its gate is run again at the next start;
#: one whose notes say it got past its gate (the service killed before it reaped the job) is not.
DUE_MARKER = "retrain.due"
#: The reason a stop gives the job it terminates.
STOPPED = "stopped with the scheduler"
#: The training episodes counted when the last job started: a start reckons its count trigger from it, so a multiple of
#: ``every_episodes`` crossed while no service ran (its last uploads during a stop, an offline ingest) still retrains.
COUNT_FILE = "retrain.count"
_BY_NOTES = ", by the notes it left"


class RetrainScheduler:
    """Starts retrain jobs when due, one at a time, each in its own process.

    ``count_episodes`` returns the number of training episodes in the catalog (so the
    schedule survives restarts); ``on_promoted(version)`` runs in the scheduler's
    thread after a job promoted a new champion (also one that ended without reporting
    after its gate promoted); ``on_finished(record)`` after every job, whatever its outcome.
    """

    def __init__(self, cfg: ScheduleConfig, data_dir: Path, count_episodes: Callable[[], int],
                 on_promoted: Callable[[str], None] = lambda version: None,
                 command: Callable[[Path, tuple[str, ...]], list[str]] = retrain_command,
                 on_finished: Callable[[RetrainRecord], None] = lambda record: None) -> None:
        self.cfg = cfg
        self.data_dir = Path(data_dir)
        self.count_episodes = count_episodes
        self.on_promoted = on_promoted
        self.on_finished = on_finished
        self.command = command
        self.history: list[RetrainRecord] = []
        """The newest ``HISTORY_KEPT`` jobs, oldest first."""
        self._jobs = 0  # started by this scheduler (its log names' suffix)
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        self._current: RetrainRecord | None = None
        # The time.monotonic() past which the running job is killed: a wall-clock step (NTP) must neither kill
        # a healthy job nor spare a stuck one. ``RetrainRecord.started`` stays the Unix time shown to users.
        self._deadline = 0.0
        self._last_count = self._counted_before(count_episodes())
        self._next_cron = self._cron_after(time.time())
        self._last_now = time.time()  # the wall clock at the last tick, to see it stepped back (``_due``)
        self._pending_manual = ""
        # The schedule's own trigger ("episodes", "cron") of a job that found another retrain holding the lock, or
        # that died midway last time: run again once the lock is free, not at the next trigger (a day later on a
        # daily cron).
        self._retry = self._died_last_time()
        self._stop = threading.Event()
        self._outlive_job = False
        self._until: threading.Event | None = None
        self._thread: threading.Thread | None = None

    # -- public -----------------------------------------------------------------
    @property
    def running(self) -> bool:
        with self._lock:
            return self._proc is not None

    @property
    def current(self) -> RetrainRecord | None:
        return self._current

    def request(self, trigger: str = "manual") -> None:
        """Ask for one retrain as soon as none is running; ``trigger`` is recorded as its reason."""
        self._pending_manual = trigger

    def start(self) -> None:
        """Run ``tick`` every ``poll_s`` in a daemon thread until ``stop``."""
        if self._next_cron is not None:  # (croniter reads Unix times in UTC, not in the machine's time zone)
            log.info("retrain on cron %r, in UTC: next at %s", self.cfg.cron,
                     time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(self._next_cron)))
        self._thread = threading.Thread(target=self._run, name="retrain-scheduler", daemon=True)
        self._thread.start()

    def stop(self, kill_running: bool = True, until: threading.Event | None = None) -> None:
        """Stop scheduling; a running job is terminated unless told otherwise (what it did by then is recorded);
        one waited for is terminated as soon as ``until`` is set (a stop signal that comes meanwhile)."""
        self._outlive_job, self._until = not kill_running, until
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if kill_running:
            self._terminate(STOPPED)
        else:
            self._wait_job()

    def _wait_job(self) -> None:
        """Wait until no job runs; terminate it once ``stop``'s ``until`` is set."""
        while not self.wait_idle(timeout=0.2):
            if self._until is not None and self._until.is_set():
                self._terminate(STOPPED)
                return

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until no job runs (polling its exit); False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.running:
            if deadline is not None and time.monotonic() > deadline:
                return False
            self._reap(block_s=0.2)
        return True

    def tick(self, now: float | None = None) -> RetrainRecord | None:
        """Reap a finished job, then start one if due. Returns the job started, if any."""
        now = time.time() if now is None else now
        self._reap()
        if self.running:
            return None
        trigger = self._due(now)
        if not trigger:
            return None
        try:
            return self._launch(trigger)
        except Exception:  # (the episodes counted once more failed): not lost, tried again at the next tick
            self._retry = self._retry or trigger
            raise

    # -- internals --------------------------------------------------------------
    def _run(self) -> None:
        failing, failed = "", 0  # the error the ticks fail with (logged once, not every poll_s), and how many did
        while not self._stop.wait(self.cfg.poll_s):
            try:
                self.tick()
            except Exception as exc:  # noqa: BLE001 -- one failure must not end scheduled retraining
                said, failed = f"{type(exc).__name__}: {exc}", failed + 1
                if said != failing:
                    log.exception("retrain scheduler: tick failed; will try again (said once until a tick passes): "
                                  "%s", said)
                failing = said
            else:
                if failing:
                    log.info("retrain scheduler: ticks pass again, after %d that failed", failed)
                failing, failed = "", 0
        if self._outlive_job:  # the job's parent-death signal comes when this thread ends (die_with_parent)
            self._wait_job()

    def _cron_after(self, t: float) -> float | None:
        return croniter(self.cfg.cron, t).get_next(float) if self.cfg.cron else None

    def _due(self, now: float) -> str:
        if self._pending_manual:
            trigger, self._pending_manual = self._pending_manual, ""
            return trigger
        if self._retry and not lock_held(self.data_dir):
            trigger, self._retry = self._retry, ""
            log.info("retrain lock free: the %s retrain that found it busy or died midway runs now", trigger)
            return trigger
        n = self.cfg.every_episodes
        # at each multiple of n, the schedule's count kept by the catalog: it holds across restarts (n more than at
        # the last start did not: a service restarted more often than it stores n episodes never retrained)
        if n and self.count_episodes() // n > self._last_count // n:
            return "episodes"
        stepped_back, self._last_now = self._last_now - now, now
        if self._next_cron is not None and stepped_back > CRON_STEP_BACK_S:
            # as cron does: a smaller step back waits for the times that already ran; after a larger one the
            # next is reckoned from now (it was hours away: a daily cron set back a day skipped that day)
            was, self._next_cron = self._next_cron, self._cron_after(now)
            log.warning("the wall clock went back %.0f s: the next cron retrain is at %s (it was at %s)", stepped_back,
                        *(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(t)) for t in (self._next_cron, was)))
        if self._next_cron is not None and now >= self._next_cron:
            self._next_cron = self._cron_after(now)
            return "cron"
        return ""

    def _died_last_time(self) -> str:
        """The schedule's trigger when the last job a scheduler started here ended before its gate because the
        service did (stopped, killed, crashed: ``DUE_MARKER`` names the job, whose own notes say how far it got; a
        job of an older release: the lock file's notes stop at "locked" or "training"), so that its retrain runs
        now rather than at the next trigger; "" otherwise."""
        trigger = "episodes" if self.cfg.every_episodes else "cron" if self.cfg.cron else ""
        info = read_lock_info(self.data_dir)
        held = False
        with contextlib.suppress(OSError):
            held = lock_held(self.data_dir)
        if held:  # (not dead: a job a killed service left running, stopped or stuck, holds it until it ends)
            log.warning("the retrain lock is held by pid %s (%s, phase %s): scheduled retrains wait until it is free; "
                        "if that process is stuck or stopped (a job left by a service that was killed), end it",
                        info.get("pid", "?"), info.get("job") or "not a scheduled job", info.get("phase", "?"))
        marked = marked_job(self.data_dir)
        if marked is not None:
            if trigger and marked:
                log.info("the last scheduled retrain here ended before its gate (%s): it runs again once the "
                         "retrain lock is free", marked)
                return trigger
            with contextlib.suppress(OSError):  # (it ended by itself, or there is no schedule now)
                (self.data_dir / DUE_MARKER).unlink()
            return ""
        if not trigger or not info.get("job") or info.get("phase") not in ("locked", "training"):
            return ""
        if not held:
            log.info("the last scheduled retrain here (pid %s) died while %s: it runs again once the retrain lock "
                     "is free", info.get("pid", "?"), info["phase"])
        return trigger

    def _counted_before(self, now: int) -> int:
        """The count at the last job's start (``COUNT_FILE``; ``now`` when none was kept or it is larger)."""
        try:
            return min(int((self.data_dir / COUNT_FILE).read_text()), now)
        except (OSError, ValueError):
            return now

    def job_args(self) -> tuple[str, ...]:
        """What each job is given after ``--data`` and ``--json``: ``--threads`` when set, then ``retrain_args``."""
        threads = ("--threads", str(self.cfg.threads)) if self.cfg.threads else ()
        return (*threads, *self.cfg.retrain_args)

    def _launch(self, trigger: str) -> RetrainRecord:
        episodes = self.count_episodes()
        self._last_count = episodes
        logs = self.data_dir / "logs"
        rec = RetrainRecord(trigger=trigger, started=time.time(), episodes=episodes, job=secrets.token_hex(8))
        self._jobs += 1
        rec.log_path = str(logs / f"retrain-{time.strftime('%Y%m%dT%H%M%S')}-{self._jobs}.log")
        try:
            logs.mkdir(parents=True, exist_ok=True)
            if trigger in ("episodes", "cron"):  # (which job: its notes tell the next start how far it got)
                (self.data_dir / DUE_MARKER).write_text(json.dumps({"trigger": trigger, "notes": str(notes_path(rec))}))
            with contextlib.suppress(OSError):
                (self.data_dir / COUNT_FILE).write_text(str(episodes))
            with open(rec.log_path + ".out", "wb") as out, open(rec.log_path, "wb") as err:
                proc = subprocess.Popen(self.command(self.data_dir, self.job_args()),  # (gone with us: see _run)
                                        stdout=out, stderr=err, stdin=subprocess.DEVNULL, preexec_fn=die_with_parent,
                                        env={**os.environ, JOB_ENV: rec.job, NOTES_ENV: str(notes_path(rec))})
        except OSError as exc:  # no log folder, no such program, no processes left: a failed job, recorded
            rec.finished, rec.status = time.time(), RetrainStatus.failed
            rec.reason = f"could not start the retrain job: {exc}"
            with self._lock:
                self._remember(rec)
            log.error("retrain failed: %s", rec.reason)
            self._notify(self.on_finished, rec)
            return rec
        with self._lock:
            self._proc, self._current = proc, rec
            self._deadline = time.monotonic() + self.cfg.timeout_s
            self._remember(rec)
        log.info("retrain started (%s, %d episodes, pid %d)", trigger, episodes, proc.pid)
        return rec

    def _remember(self, rec: RetrainRecord) -> None:
        """Under ``_lock``: ``rec`` at the end of ``history``, which keeps the newest ``HISTORY_KEPT``."""
        self.history.append(rec)
        del self.history[:-HISTORY_KEPT]

    def _prune_logs(self, current: RetrainRecord) -> None:
        """Delete the logs of all but the newest ``LOGS_KEPT`` jobs (by modification time; never ``current``'s)."""
        now = time.time()
        logs = sorted(self.data_dir.glob("logs/retrain-*.log"), key=lambda p: (-age_s(p, now), p.name))
        for old in logs[:-LOGS_KEPT]:
            if str(old) == current.log_path:
                continue
            for path in (old, Path(f"{old}.out"), Path(f"{old}.notes")):  # (notes: a killed service's job left them)
                with contextlib.suppress(OSError):
                    path.unlink(missing_ok=True)

    def _reap(self, block_s: float = 0.0) -> None:
        with self._lock:
            proc, rec, deadline = self._proc, self._current, self._deadline
        if proc is None or rec is None:
            return
        try:
            rc = proc.wait(timeout=block_s) if block_s else proc.poll()
        except subprocess.TimeoutExpired:
            rc = None
        if rc is None:
            if time.monotonic() > deadline:
                self._terminate(f"timed out after {self.cfg.timeout_s:.0f} s", RetrainStatus.timeout)
            return
        self._finish(proc, rec, rc)

    def _terminate(self, why: str, status: RetrainStatus = RetrainStatus.killed) -> None:
        with self._lock:
            proc, rec = self._proc, self._current
        if proc is None or rec is None:
            return
        proc.send_signal(signal.SIGTERM)
        try:
            rc = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            rc = proc.wait()
        self._finish(proc, rec, rc, status=status, reason=why)

    def _finish(self, proc: subprocess.Popen, rec: RetrainRecord, rc: int,
                status: RetrainStatus | None = None, reason: str = "") -> None:
        with self._lock:
            if self._proc is not proc:
                return  # another thread finished it first
            self._proc = None
        rec.finished, rec.returncode = time.time(), rc
        result = last_json(Path(rec.log_path + ".out"))
        reported = rc == 0 and bool(result)
        if reported:  # also when a stop or the timeout came after it had exited: it finished
            rec.version = str(result.get("version", ""))
            rec.metrics = dict(result.get("metrics") or {})
            rec.status = RetrainStatus.promoted if result.get("promoted") else RetrainStatus.rejected
            rec.reason = str(result.get("reason", ""))
        elif status is not None:
            rec.status, rec.reason = status, reason
        elif rc == EXIT_BUSY:
            rec.status, rec.reason = RetrainStatus.busy, log_tail(Path(rec.log_path))
        elif rc < 0:
            rec.status = RetrainStatus.killed
            rec.reason = f"killed by {signal_name(-rc)}"
        else:
            rec.status = RetrainStatus.failed
            rec.reason = f"exit status {rc}: {log_tail(Path(rec.log_path))}"
        gated = reported or self._read_what_it_left(proc.pid, rec)
        if gated or reason != STOPPED:  # (a stop before the gate keeps it: the next start runs the retrain again)
            with contextlib.suppress(OSError):
                (self.data_dir / DUE_MARKER).unlink(missing_ok=True)
        for path in (notes_path(rec), Path(f"{notes_path(rec)}.tmp")):  # read once; (.tmp: a job killed while noting)
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)
        level = logging.INFO if reported else logging.WARNING
        pruned = (result.get("pruned") or []) if reported else []
        log.log(level, "retrain %s%s: %s%s", rec.status.value, f" {rec.version}" if rec.version else "",
                rec.reason.removeprefix(f"{rec.status.value}: ") or "-",
                f" (pruned the files of {len(pruned)} older models)" if pruned else "")
        if reported and result.get("prune_error"):
            log.warning("retrain %s: %s", rec.version or "-", result["prune_error"])
        if reported and result.get("quarantined"):
            log.warning("retrain %s: %s", rec.version or "-", quarantined_note([str(i) for i in result["quarantined"]]))
        for line in (result.get("warnings") or []) if reported else []:  # e.g. a warm start past a damaged champion
            log.warning("retrain %s: %s", rec.version or "-", line)
        self._prune_logs(rec)
        if rec.status is RetrainStatus.busy and rec.trigger in ("episodes", "cron"):  # (a requester sees its record)
            self._retry = rec.trigger
            log.info("retrain (%s) runs again once the retrain lock is free", rec.trigger)
        if rec.status is RetrainStatus.promoted:
            self._notify(self.on_promoted, rec.version)
        self._notify(self.on_finished, rec)

    @staticmethod
    def _notify(callback: Callable[[Any], None], arg: Any) -> None:
        """``on_promoted`` / ``on_finished``: what they do (publish an event, reload the scorer, count) is news,
        not the retrain's record; one that raises (a registry read that failed) is logged, and neither the
        scheduler's thread nor a stop that finishes a job (``stop`` after a service's Ctrl-C) ends with it."""
        try:
            callback(arg)
        except Exception:  # noqa: BLE001 -- boundary: a listener's failure is its own
            log.exception("retrain: %s failed", getattr(callback, "__name__", "a callback"))

    def _read_what_it_left(self, pid: int, rec: RetrainRecord) -> bool:
        """Complete the record of a job that ended without reporting: its notes file names the model it registered
        (when it got that far; failing that, the lock file, when no job has taken the lock since), the registry
        what its gate made of it. A promotion is recorded as one, with how the job ended, so that the history and
        ``on_promoted`` follow the champion; a rejection, which changed nothing, keeps the job's own ending."""
        own = read_holder(notes_path(rec))  # ({} when the job wrote none)
        info = own if own.get("version") else read_lock_info(self.data_dir)
        version = info.get("version")
        if info.get("job") != rec.job or info.get("pid") != pid or not isinstance(version, str) or not version:
            return False  # (the job id, not the pid alone: an earlier holder's notes may carry a pid used again)
        rec.version, ended = version, rec.reason
        try:
            registry = ModelRegistry(self.data_dir)
            model = registry.get(version)
            promotions = [entry.reason for entry in registry.history() if entry.version == version]
        except (StorageError, OSError) as exc:
            rec.reason = f"{ended}; it had registered {version}, whose gate's verdict cannot be read now: {exc}"
            return False
        rec.metrics = {k: v for k, v in model.metrics.items() if not isinstance(v, (list, dict))}
        if promotions:
            rec.status = RetrainStatus.promoted
            rec.reason = f"{promotions[-1]} (then the job ended without reporting it: {ended})"
        elif model.status is ModelStatus.REJECTED:
            rec.reason = f"{ended}, after its gate had rejected {version}: {model.reason}"
        else:
            rec.reason = f"{ended} before its gate judged {version} (the next retrain rejects it as abandoned)"
            return False
        return True


def read_marker(data_dir: Path) -> dict | None:
    """``DUE_MARKER`` in ``data_dir`` (``{}`` when it cannot be read, or holds no object); None without one."""
    try:
        marker = json.loads((data_dir / DUE_MARKER).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        marker = {}
    return marker if isinstance(marker, dict) else {}


def marked_job(data_dir: Path, registry_dir: Path | None = None, marker: dict | None = None) -> str | None:
    """How far the job ``DUE_MARKER`` in ``data_dir`` names got when the service ended ("" when it got past its gate,
    or failed by itself: nothing to run again); None without a marker. Its model is looked up in the registry of
    ``registry_dir`` (default ``data_dir``; a backup's copy); ``marker``: as read earlier (None: read it now)."""
    marker = read_marker(data_dir) if marker is None else marker
    if marker is None:
        return None
    if not marker.get("notes") and isinstance(marker.get("copied"), str):  # a backup's: see ``carry_schedule``
        return marker["copied"]
    named = marker.get("notes")  # (a hand-edited marker may hold anything: a job to run again, not a crash)
    notes = read_holder(Path(named)) if isinstance(named, str) and named else {}
    phase, version = notes.get("phase"), notes.get("version")
    if phase == "failed":
        return ""
    if isinstance(version, str) and version:
        gated = _gated(registry_dir or data_dir, version)  # (None: cannot tell: run it again rather than lose it)
        if gated:
            return ""  # gated: promoted or rejected
        if phase == "done" and registry_dir is not None and (gated is False or _gated(data_dir, version) is not None):
            # a copy's snapshot taken before the gate the notes, read after it, report: not gated in the copy
            return "gated after the snapshot"
    return "" if phase == "done" else f"{phase or 'starting'}{_BY_NOTES}"


def _gated(registry_dir: Path, version: str) -> bool | None:
    """Whether ``version`` is past its gate (promoted or rejected) in ``registry_dir``'s registry; None when it is not
    there or cannot be read."""
    try:
        return ModelRegistry(registry_dir).get(version).status != ModelStatus.CANDIDATE
    except (StorageError, OSError):
        return None


def carry_schedule(source: Path) -> Callable[[Path], None]:
    """Read ``source``'s retrain schedule before a backup's snapshot; the function returned gives ``copy``, the
    backup with its catalog and registry snapshotted, that schedule: ``COUNT_FILE`` as it was, so a multiple of
    ``--retrain-every`` reached before the snapshot and not yet retrained is retrained where the copy serves, and
    ``DUE_MARKER`` when the job it named had not passed its gate in the snapshot (its model not gated in the copy's
    registry, or not in it), so the copy runs that job again. Read before, not after: a job whose gate came between
    the snapshot and the read had its marker deleted by then, and the copy's candidate was never gated.
    The copy's marker names no notes (they stay with ``source``'s logs): it says how far the job had got."""
    count = None
    with contextlib.suppress(OSError, ValueError):  # (none kept: the copy reckons from its own count, as here)
        count = int((source / COUNT_FILE).read_text())
    marker = read_marker(source)

    def carry(copy: Path) -> None:
        if count is not None:
            write_synced(copy / COUNT_FILE, str(count).encode())
        marked = marked_job(source, copy, marker) if marker is not None else None  # (its notes as they are now)
        if marked:
            copied = marked.removesuffix(_BY_NOTES)
            if not copied.endswith(" was backed up"):  # (a backup of a backup keeps the first one's words)
                copied = f"{copied}, when {source.resolve()} was backed up"
            write_synced(copy / DUE_MARKER, json.dumps({"copied": copied}).encode())

    return carry
