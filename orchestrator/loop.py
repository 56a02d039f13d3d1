"""The closed loop on one machine: collect -> score -> plan -> retrain -> promote -> hot-swap.

Parts, each usable alone (the champion scorer is ``orchestrator.champion``'s, the
configuration ``orchestrator.loopconfig.RunConfig``):

- ``RoundPlanner`` (``orchestrator.loop_rounds``): the service's planner in lockstep rounds:
  it keeps each round's episodes and plans the next round when a retrain has finished.
- ``LoopRun``: ``activecollect run``: the service, N worker processes over Zenoh on
  loopback, the eval split, the seed requests, the retrain scheduler, the dashboard
  and a progress line, until the episode budget is spent; then the report. Ctrl-C
  and SIGTERM stop it early the same way: workers drained, a running retrain stopped,
  the report written; once it stops (early or not), a further one cannot cut that short
  (it stops a running retrain, and the report is still written). The workers are told to drain with
  ``workers.agent.DRAIN_SIGNAL``, never with a stop signal: a terminal's Ctrl-C,
  systemd's stop and ``kill -TERM -PGID`` reach them too, and a second stop signal
  would make them give their episode back unfinished.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from tqdm import tqdm

from orchestrator.champion import ChampionScorer, FramesSource
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources, learning_curve
from orchestrator.loop_catalog import eval_leftovers_warning, load_episodes
from orchestrator.loop_rounds import RoundPlanner
from orchestrator.loopconfig import RunConfig
from orchestrator.metrics import ServiceMetrics, retrain_outcome
from orchestrator.planner import ActivePlanner, ActivePlannerConfig, Planner, in_eval_split
from orchestrator.uniform import UniformPlanner, UniformPlannerConfig
from orchestrator.protocol import EventKind
from orchestrator.report import ReportInputs, write_report
from orchestrator.retrainjob import RetrainRecord, RetrainStatus, ScheduleConfig, die_with_parent
from orchestrator.retrainlock import lock_held
from orchestrator.scheduler import RetrainScheduler
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from orchestrator.signals import on_stop_signals
from storage.catalog import Catalog
from storage.models import ModelRegistry, ModelStatus
from storage.queue import RequestQueue, steady_clock
from storage.records import Episode
from workers.agent import DRAIN_SIGNAL

log = logging.getLogger(__name__)


#: Creates (or checks) the pinned eval split: (catalog, episodes, seed, steps, image size) -> its hash.
MakeEvalSplit = Callable[[Catalog, int, int, int, int], str]


def worker_command(endpoint: str, namespace: str, worker_id: str, image_size: int) -> list[str]:
    """One worker process connected to the service on loopback.

    ``python -m workers.agent`` takes the flags of ``activecollect worker`` but never
    imports torch: a worker starts in about a second and holds a fraction of the memory.
    """
    return [sys.executable, "-m", "workers.agent", "--connect", endpoint, "--namespace", namespace,
            "--id", worker_id, "--size", str(image_size)]


#: A worker's log (``DATA/logs/run-w<i>.log``, appended to by every run) found larger than this when a run starts
#: is moved to ``run-w<i>.log.1``, replacing the one there: at most two files per worker index, however many runs.
WORKER_LOG_BYTES = 10 * 2**20


def worker_log(logs: Path, worker_id: str) -> Path:
    """The log ``worker_id``'s output is appended to in ``logs``, first rotated to ``<name>.1`` when it holds more
    than ``WORKER_LOG_BYTES``."""
    path = logs / f"{worker_id}.log"
    try:
        if path.stat().st_size > WORKER_LOG_BYTES:
            os.replace(path, path.with_name(f"{path.name}.1"))
    except FileNotFoundError:  # the first run in this directory
        pass
    return path


@dataclass
class RunResult:
    """What ``activecollect run`` did."""

    report: Path
    episodes: int
    """Training episodes in the catalog (what ``--budget`` counts: earlier runs' too, and quarantined ones)."""
    collected: int
    """Of those, the ones this run added."""
    champion: str | None
    champion_h1_mse: float | None
    retrains: list[dict]
    seconds: float
    interrupted: bool

    def to_json(self) -> dict:
        d = asdict(self)
        d["report"] = str(self.report)
        return d


class LoopRun:
    """``activecollect run``: see the module docstring. ``run()`` blocks until done or Ctrl-C."""

    def __init__(self, cfg: RunConfig, make_eval_split: MakeEvalSplit,
                 worker_cmd: Callable[[str, str, str, int], list[str]] | None = None,
                 announce: Callable[[str], None] = lambda line: None) -> None:
        self.cfg = cfg
        self.make_eval_split = make_eval_split
        self.worker_cmd = worker_cmd or worker_command  # (looked up now: a test may give workers that fail)
        self.announce = announce
        """Told one-line news for the operator (where the dashboard is)."""
        self.metrics = ServiceMetrics()
        self.procs: list[subprocess.Popen] = []
        self.service: Service | None = None
        self.dashboard: Dashboard | None = None
        self._shown: tuple[str, int] = ("", -1)
        self._at_start: int | None = None
        """Training episodes in the catalog when this run began (a resumed run's report tells its own apart)."""
        self._terminated = threading.Event()
        """Set by SIGTERM, and by Ctrl-C once ``_take_ctrl_c`` has it: stop."""
        self._ctrl_c = False
        """A Ctrl-C stopped the loop (once ``_take_ctrl_c`` has it; before, it is a KeyboardInterrupt)."""
        self._stopping = False
        """The loop is over (early or not): a stop signal now can only hurry the tear-down, never end the run."""
        self._stop_lock = threading.Lock()  # (between the two above: a Ctrl-C either stopped the loop or came after)
        self._give_back_ctrl_c: Callable[[], None] | None = None
        self._busy: tuple[RetrainRecord | None, bool] = (None, False)
        """The last busy retrain record ``_lock_freed`` saw, and whether the loop asked for it again."""
        self._clock = steady_clock()
        """One clock for this run's queue writes, its own (top-ups, cancels) and its service's (``steady_clock``):
        after a step of the wall clock, their ``created`` and ``updated`` stamps still agree."""

    # -- set-up ---------------------------------------------------------------------------------
    def _setup(self) -> None:
        cfg = self.cfg
        endpoint = f"tcp/127.0.0.1:{cfg.zenoh_port or free_port()}"
        self.service = Service(ServiceConfig(data_dir=cfg.data_dir, namespace=cfg.namespace, listen=(endpoint,),
                                             lease_s=cfg.lease_s, planner=lambda ctx: self.planner,
                                             metrics=self.metrics), wall_clock=self._clock)
        self.service.claim()  # before anything writes: a directory a `serve` serves is refused, left as it was
        self.catalog = Catalog(cfg.data_dir)
        self.queue = RequestQueue(self.catalog.db_path, clock=self._clock)
        self.registry = ModelRegistry(cfg.data_dir)
        self._at_start = self._count()
        self.make_eval_split(self.catalog, cfg.eval_episodes, cfg.eval_seed, cfg.steps, cfg.image_size)
        if leftovers := eval_leftovers_warning(self.catalog):
            log.warning("%s", leftovers)
        if self._terminated.is_set():  # (during the eval split: set-up's slow part)
            return
        self._cancel_leftovers()
        self.scorer = ChampionScorer(cfg.data_dir, observe=self.metrics.observe_scoring)
        rng = np.random.default_rng(cfg.seed + self.catalog.count(split="train"))  # a resumed run draws anew
        depth = lambda: self.queue.counts().get("queued", 0)  # noqa: E731
        uniform = UniformPlannerConfig(steps=cfg.steps, max_queue_depth=cfg.round_episodes)
        inner: Planner = (UniformPlanner(uniform, rng, depth) if cfg.planner == "uniform" else ActivePlanner(
            ActivePlannerConfig(steps=cfg.steps, budget_per_round=cfg.round_episodes,
                                max_queue_depth=cfg.round_episodes, seed_uniform=uniform), self.scorer, rng, depth,
            is_eval=in_eval_split(self.catalog)))
        if isinstance(inner, ActivePlanner):  # a resumed run keeps away from the states it asked for before
            inner.remember_queue(self.queue)
        self.planner = RoundPlanner(inner, cfg.round_episodes, cfg.budget, self._count, self._outstanding)
        # Workers first, while this process has no other threads yet but the stop-signals one, which
        # holds no lock (see die_with_parent); they retry until the service below answers.
        logs = cfg.data_dir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        for i in range(cfg.workers):
            wid = f"run-w{i}"
            with open(worker_log(logs, wid), "ab") as out:
                self.procs.append(subprocess.Popen(self.worker_cmd(endpoint, cfg.namespace, wid, cfg.image_size),
                                                   stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                                   preexec_fn=die_with_parent))
        self.service.start()
        self.scheduler = RetrainScheduler(
            # the rounds decide when to retrain (see _wait_until_done), so no count trigger here
            ScheduleConfig(timeout_s=cfg.retrain_timeout_s, retrain_args=cfg.retrain_args),
            cfg.data_dir, self._count, on_promoted=self._promoted, on_finished=self._retrained)
        self.scheduler.start()
        if cfg.dashboard_port >= 0:
            self._start_dashboard()

    def _cancel_leftovers(self) -> None:
        """Cancel the queued requests an earlier run (killed, or with a larger ``--round``) or a ``serve`` left beyond
        the rest of this run's current round within its budget: the loop collects everything queued before it
        retrains or stops, so they would overshoot both. Leased ones stay (this run's workers have the same ids
        and take theirs back at once; another's lease runs out and goes back to the queue)."""
        count, cfg = self._count(), self.cfg
        round_left = cfg.round_episodes - count % cfg.round_episodes
        keep = max(0, min(cfg.budget - count, round_left) - self.queue.counts().get("leased", 0))
        extra = self.queue.list(status="queued")[keep:]  # (in the order they would be leased: the best kept)
        for request in extra:
            self.queue.cancel(request.id)
        if extra:
            log.warning("cancelled %d queued request(s) left by an earlier run: beyond this run's round or budget "
                        "(%d training episodes of %d, round of %d)", len(extra), count, cfg.budget, cfg.round_episodes)

    def _start_dashboard(self) -> None:
        src = DataSources(self.cfg.data_dir, workers=lambda: [{"id": w} for w in self.service.workers()],
                          # (the service's: its reaper keeps the gauges of the stores fresh, as `serve`'s; read
                          # here, the run's queue kept a connection per request's thread: 2 descriptors leaked each)
                          metrics_text=self.metrics.render, frames_png=FramesSource(self.scorer, self.catalog),
                          budget=self.cfg.budget, retrains=lambda: [r.to_json() for r in self.scheduler.history])
        dash = Dashboard(DashboardConfig(port=self.cfg.dashboard_port), src.sources())
        try:
            dash.start()
        except OSError as exc:  # a busy port must not stop the run
            log.warning("no dashboard: cannot bind 127.0.0.1:%d: %s", self.cfg.dashboard_port, exc)
            return
        self.dashboard = dash
        self.announce(f"dashboard at {dash.url}")

    # -- callbacks ------------------------------------------------------------------------------
    def _count(self) -> int:
        """Training episodes in the catalog, quarantined ones too: what ``--budget`` counts."""
        return self.catalog.count(split="train")

    def _trainable(self) -> int:
        """Training episodes a retrain can load: ``_count`` less the quarantined."""
        return self.catalog.count(split="train", quarantined=False)

    def _outstanding(self) -> int:
        counts = self.queue.counts()
        return counts.get("queued", 0) + counts.get("leased", 0)

    def _promoted(self, version: str) -> None:
        self.scorer.reload()
        h1 = self.registry.get(version).metrics.get("h1_mse")  # the service's gauges read the registry themselves
        self.service.publish(EventKind.MODEL_PROMOTED, {"version": version, "h1_mse": h1})

    def _retrained(self, rec: RetrainRecord) -> None:
        self.metrics.retrain(retrain_outcome(rec.status.value))

    # -- the loop -------------------------------------------------------------------------------
    def run(self) -> RunResult:
        """Collect until the budget is spent and the last retrain is done; then write the report.

        Ctrl-C or SIGTERM (taken while this runs, on the main thread) stop it early: the workers finish
        and upload the episode in hand, a running retrain is stopped, the report is written, and the
        result says ``interrupted``. One that comes once the loop is over (early or not) stops a
        running retrain and is logged; the report is still written.
        """
        restore = on_stop_signals(self._terminated.set, sigint=False)  # Ctrl-C: see _take_ctrl_c
        try:
            return self._run()
        finally:
            restore()

    def _take_ctrl_c(self) -> None:
        """From now on Ctrl-C is ``_on_ctrl_c``'s (on the stop-signals thread), no longer a KeyboardInterrupt: that
        one interrupts set-up's slow part (the eval split), but raised in the tear-down or while the report is
        written it lost the report. Unless SIGINT was ignored when the run began (``on_stop_signals``)."""
        if self._give_back_ctrl_c is None and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
            self._give_back_ctrl_c = on_stop_signals(self._terminated.set, sigint=False,
                                                     also={signal.SIGINT: self._on_ctrl_c})

    def _on_ctrl_c(self) -> None:
        with self._stop_lock:
            stopping = self._stopping
            self._ctrl_c = self._ctrl_c or not stopping
        self._terminated.set()  # (once stopping: a running retrain is stopped, see _teardown)
        if stopping:
            log.warning("Ctrl-C: stopping already; a running retrain is stopped, the rest of the stop is not cut short")

    def _run(self) -> RunResult:
        start = time.monotonic()  # a duration: a step of the wall clock (NTP) must not make it wrong or negative
        ctrl_c = False
        try:
            try:
                self._setup()
                self._take_ctrl_c()
                if not self._terminated.is_set():
                    self._wait_until_done()
            except KeyboardInterrupt:
                ctrl_c = True
            finally:
                self._take_ctrl_c()  # first: a Ctrl-C from here on must not cut the tear-down or the report short
                with self._stop_lock:
                    self._stopping = True
                    ctrl_c = ctrl_c or self._ctrl_c
                    interrupted = ctrl_c or self._terminated.is_set()
                if interrupted:
                    log.warning("interrupted (%s): stopping workers; the next run resumes from the catalog",
                                "Ctrl-C" if ctrl_c else "SIGTERM")
                self._teardown(interrupted)
            return self._finish(start, interrupted)
        finally:
            if self.service is not None:  # last: no `serve` starts on the directory while the report is written
                self.service.release_claim()
            if self._give_back_ctrl_c is not None:  # (before run()'s restore: the reverse order of installing)
                self._give_back_ctrl_c()

    def _all_trained(self) -> bool:
        """Whether a finished retrain saw every training episode: the last of this run's saw the catalog's count
        (which only grows), or, before any, this run collected nothing yet and a model of an earlier run saw every
        episode a retrain can load (``_trainable``: not the quarantined, which ``_count`` holds; a directory with
        one was retrained on every run). A model saw those it trained on and those it left out for their frame
        size or as replays of eval episodes. A candidate is not finished: its job died before the gate (an earlier
        run SIGKILLed), and the round is retrained. A job that found the retrain lock held trained nothing (see
        ``_lock_freed``); one that failed otherwise counts, or a retrain that fails every time would hold the run
        for ever."""
        done = [r for r in self.scheduler.history if r.finished is not None and r.status is not RetrainStatus.busy]
        if done:
            return done[-1].episodes >= self._count()
        seen = [sum(int(m.metrics.get(key, 0)) for key in ("train_episodes", "train_replays_left_out",
                                                            "train_other_size_left_out"))
                for m in self.registry.list() if m.status is not ModelStatus.CANDIDATE]
        return self._count() == self._at_start and max(seen, default=0) >= self._trainable()

    def _lock_freed(self) -> bool:
        """Whether the round's retrain found the retrain lock held by another retrain (a cron job's, an operator's)
        and the lock is free now: then it is asked for again, as ``serve``'s scheduled retrains are."""
        last = self.scheduler.history[-1] if self.scheduler.history else None
        if last is None or last.status is not RetrainStatus.busy or self._busy == (last, True):
            return False
        if lock_held(self.cfg.data_dir):
            if self._busy[0] is not last:
                log.warning("the round's retrain found the retrain lock held by another retrain: it runs once the "
                            "lock is free (the run waits for it; Ctrl-C stops the run, and the next one retrains)")
                self._busy = (last, False)
            return False
        self._busy = (last, True)
        log.info("retrain lock free: the round's retrain that found it held runs now")
        return True

    def _wait_until_done(self) -> None:
        cfg = self.cfg
        bar = tqdm(total=cfg.budget, unit="ep", desc=f"run ({cfg.planner})", disable=not cfg.progress,
                   file=sys.stderr, dynamic_ncols=True)
        asked_for = -1
        try:
            while True:
                count, running = self._count(), self.scheduler.running
                self._show(bar, count)
                if not running and self._outstanding() == 0:
                    if self._all_trained():  # a retrain (this run's or an earlier one's) saw them all
                        if count >= cfg.budget:
                            return
                        self._release()
                    elif count >= cfg.budget or count % cfg.round_episodes == 0:
                        if asked_for != count or self._lock_freed():  # complete: retrain, then plan the next
                            self.scheduler.request("round")
                            asked_for = count
                    else:  # mid-round and nothing outstanding (a request died): fill this round only
                        self._release(cfg.round_episodes - count % cfg.round_episodes)
                self._check_workers()
                if self._terminated.wait(0.5):  # (0.5 s: the progress line's refresh period)
                    return
        finally:
            self._show(bar, self._count())
            bar.close()

    def _release(self, limit: int | None = None) -> None:
        if not self.planner.has_episodes():
            latest = self.catalog.list(split="train", limit=self.cfg.round_episodes, newest_first=True,
                                       quarantined=False)[::-1]
            self.planner.remember(load_episodes(self.catalog, [r.episode_id for r in latest], "the next round's plan"))
        made = 0
        for request, created in self.queue.enqueue_many(self.planner.release(limit)):
            made += created
            if created:
                self.service.publish(EventKind.REQUEST_QUEUED, {
                    "request_id": request.id, "status": request.status.value, "priority": request.priority,
                    "shape": request.shape, "source": request.reason.get("planner", self.planner.name)})
        log.info("released %s of %d requests", "a round" if limit is None else "the rest of a round", made)

    def _check_workers(self) -> None:
        dead = [p for p in self.procs if p.poll() is not None]
        if len(dead) == len(self.procs) and not self._terminated.is_set():  # (a SIGTERM to the whole group)
            raise LoopError(f"all {len(self.procs)} workers exited (codes {[p.returncode for p in dead]}); "
                            f"see {self.cfg.data_dir / 'logs'}")

    def _show(self, bar: tqdm, count: int) -> None:
        counts = self.queue.counts()
        champion = self.scorer.version or self.registry.champion()
        h1 = self.registry.get(champion).metrics.get("h1_mse") if champion else None
        last = self.scheduler.history[-1] if self.scheduler.history else None
        retrain = f"{last.status.value}@{last.episodes}" if last else "none"
        text = (f"queue {counts.get('queued', 0)}+{counts.get('leased', 0)} | workers "
                            f"{len(self.service.workers())}/{len(self.procs)} | champion {champion or '-'}"
                            f"{f' h1 {h1:.2e}' if h1 is not None else ''} | retrain {retrain}")
        if (text, count) != self._shown:  # redraw on change only: quiet in logs
            self._shown = (text, count)
            bar.n = min(count, bar.total)
            bar.set_postfix_str(text, refresh=True)

    # -- tear-down ------------------------------------------------------------------------------
    def _teardown(self, interrupted: bool) -> None:
        """Stop the workers (each finishes and uploads its episode), the dashboard, the scheduler (a running
        retrain too when ``interrupted``) and the service."""
        for p in self.procs:  # drain, and nothing more for one that a stop signal reached already
            if p.poll() is None:
                p.send_signal(DRAIN_SIGNAL)
        for p in self.procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if self.dashboard is not None:
            self.dashboard.stop()
        if hasattr(self, "scheduler"):  # (a stop signal since the loop ended: stop a running retrain too)
            self.scheduler.stop(kill_running=interrupted or self._terminated.is_set(), until=self._terminated)
        if self.service is not None:
            self.service.stop(keep_claim=True)  # (let go once the report is written: see _run)

    def _finish(self, start: float, interrupted: bool) -> RunResult:
        if not hasattr(self, "scheduler"):  # interrupted during set-up: open what it had not opened yet
            if hasattr(self, "queue"):
                self.queue.close()
            self.catalog = Catalog(self.cfg.data_dir)
            self.queue = RequestQueue(self.catalog.db_path, clock=self._clock)
            self.registry = ModelRegistry(self.cfg.data_dir)
        champion = self.registry.champion()
        scorer: ChampionScorer | None = getattr(self, "scorer", None)
        ensemble, problem = None, None
        if champion is not None and scorer is not None:
            scorer.reload()
            loaded, ensemble = scorer.loaded()
            if loaded != champion:  # the champion cannot be loaded: no frames of another model under its name
                ensemble, problem = None, scorer.problem or f"champion {champion} is not the model loaded"
        h1 = self.registry.get(champion).metrics.get("h1_mse") if champion else None
        retrains = [r.to_json() for r in self.scheduler.history] if hasattr(self, "scheduler") else []
        count = self._count()
        collected = 0 if self._at_start is None else count - self._at_start  # (stopped before set-up counted)
        train_sample, eval_sample = self._samples()  # (first: what they find lost is quarantined, and counted below)
        summary = {"planner": self.cfg.planner, "episodes": count,
                   "quarantined": self.catalog.count(split="train", quarantined=True), "collected_this_run": collected,
                   "budget": self.cfg.budget, "round_episodes": self.cfg.round_episodes, "workers": self.cfg.workers,
                   "image_size": self.cfg.image_size, "steps": self.cfg.steps, "champion": champion,
                   "champion_h1_mse": h1, "retrains": len(retrains), "interrupted": interrupted,
                   "seconds": round(time.monotonic() - start, 1), "queue": self.queue.counts()}
        if problem is not None:
            summary["champion_problem"] = problem
        if interrupted:  # (what was left to do: the report's headline says it)
            summary["interrupted_in"] = ("set-up" if not hasattr(self, "scheduler") else
                                         "collection" if count < self.cfg.budget else "the last retrain")
        inputs = ReportInputs(curve=learning_curve(self.catalog, self.registry), summary=summary, retrains=retrains,
                              champion=ensemble, train_sample=train_sample, eval_sample=eval_sample)
        report = write_report(self.cfg.data_dir, inputs)
        self.queue.close()
        return RunResult(report=report, episodes=count, collected=collected, champion=champion, champion_h1_mse=h1,
                         retrains=retrains, seconds=summary["seconds"], interrupted=interrupted)

    def _samples(self) -> tuple[list[Episode], list[Episode]]:
        """The report's episodes: the newest training ones of the run's frame size (a catalog older than the
        one-frame-size rule may hold others) and the first eval ones; those whose files are lost are left out."""
        rows = self.catalog.list(split="train", limit=40, newest_first=True, quarantined=False)
        train = load_episodes(self.catalog, [r.episode_id for r in rows], "the report")
        split = self.catalog.eval_split()
        return ([ep for ep in train if ep.frames.shape[1] == self.cfg.image_size],
                load_episodes(self.catalog, split.ids[:3] if split else [], "the report", quarantine=False))


class LoopError(Exception):
    """The loop cannot go on (every worker died, the service would not start)."""


def free_port() -> int:
    """A loopback TCP port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
