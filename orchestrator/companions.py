"""What runs beside the service in ``activecollect serve``: the dashboard and the retrain scheduler.

``activecollect run`` drives retraining in rounds itself (see ``orchestrator.loop``);
a long-running ``serve`` instead retrains every N new training episodes and/or on a
cron expression, one job at a time in a child process, so leasing never stalls. The
champion scorer reloads a promoted model on its next call (hot swap), so a promotion
only has to be announced. Nothing here imports torch: retrains run in child processes,
and the scorer loads it with the first champion.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

from orchestrator.champion import ChampionScorer, FramesSource
from orchestrator.dashboard import Dashboard, DashboardConfig, DataSources
from orchestrator.metrics import retrain_outcome
from orchestrator.protocol import EventKind
from orchestrator.retrainjob import RetrainRecord, ScheduleConfig
from orchestrator.scheduler import RetrainScheduler
from orchestrator.service import Service

log = logging.getLogger(__name__)


def fitted_retrain_threads(scoring_threads: int, cores: int | None = None) -> int:
    """The retrain job's torch threads that, with the scoring's, fill the machine's cores (at least 1);
    0 (torch's default) when the scoring takes torch's default itself: there is nothing to fit."""
    if not scoring_threads:
        return 0
    return max(1, (cores or len(os.sched_getaffinity(0))) - scoring_threads)


@dataclass
class CompanionConfig:
    """The dashboard and the retrain schedule of ``activecollect serve``."""

    dashboard_port: int = 8765
    """Dashboard port on ``dashboard_host`` (0 = any free port, -1 = no dashboard)."""
    dashboard_host: str = "127.0.0.1"
    """Address the dashboard binds; it has no authentication, so keep it local."""
    dashboard_max_connections: int = DashboardConfig.max_connections
    """Dashboard connections served at once (``DashboardConfig.max_connections``)."""
    dashboard_request_timeout_s: float = DashboardConfig.request_timeout_s
    """How long a dashboard client may take to send its request (``DashboardConfig.request_timeout_s``)."""
    retrain_every: int = 0
    """Retrain each time the training episode count crosses a multiple of this (0 = not on count)."""
    retrain_cron: str = ""
    """Also retrain on this cron expression, e.g. ``0 * * * *`` ('' = not on time)."""
    retrain_timeout_s: float = ScheduleConfig.timeout_s
    """A retrain running longer than this is killed (``ScheduleConfig.timeout_s``; ``serve --retrain-timeout``)."""
    retrain_args: tuple[str, ...] = ()
    """Extra ``activecollect retrain`` arguments (training and gate settings)."""
    retrain_threads: int | None = None
    """Torch threads of each retrain job (``ScheduleConfig.threads``; 0 = torch's default, one per core; None,
    set at construction: the cores the scoring leaves, ``fitted_retrain_threads``)."""
    scoring_threads: int = 0
    """Torch threads of the dashboard's champion (``ChampionScorer.threads``; 0 = torch's default)."""

    def __post_init__(self) -> None:
        if not -1 <= self.dashboard_port <= 65535:
            raise ValueError(f"dashboard_port must be -1 (none) or in [0, 65535], found {self.dashboard_port}")
        self.dashboard_config()  # its own checks, before anything starts
        if self.scoring_threads < 0:
            raise ValueError(f"scoring_threads must be >= 0, found {self.scoring_threads}")
        if self.retrain_threads is None:
            self.retrain_threads = fitted_retrain_threads(self.scoring_threads)
        if self.retrain_every < 0:
            raise ValueError(f"retrain_every must be >= 0, found {self.retrain_every}")
        # The schedule's own checks (cron syntax, timeout), before anything starts.
        self.schedule()

    def schedule(self) -> ScheduleConfig:
        """The retrain schedule's settings (raises ValueError for a bad one)."""
        return ScheduleConfig(every_episodes=self.retrain_every, cron=self.retrain_cron,
                              timeout_s=self.retrain_timeout_s, retrain_args=self.retrain_args,
                              threads=self.retrain_threads)

    def dashboard_config(self) -> DashboardConfig:
        """The dashboard's settings (raises ValueError for a bad one; port -1, no dashboard, gives 0)."""
        return DashboardConfig(host=self.dashboard_host, port=max(self.dashboard_port, 0),
                               max_connections=self.dashboard_max_connections,
                               request_timeout_s=self.dashboard_request_timeout_s)


class Companions:
    """Starts and stops the dashboard and the scheduler around a started ``Service``."""

    def __init__(self, cfg: CompanionConfig, service: Service) -> None:
        self.cfg = cfg
        self.service = service
        self.scheduler: RetrainScheduler | None = None
        self.dashboard: Dashboard | None = None
        self.scorer: ChampionScorer | None = None
        """The dashboard's champion (for its predicted-vs-real frames): the planner's when it has one."""

    def start(self) -> None:
        """Raises ``ValueError`` for a bad schedule, ``StorageError`` when the catalog cannot be read (the
        scheduler counts its training episodes) and ``OSError`` when the dashboard port is taken. What it had
        started by then is left to ``stop``."""
        cfg, ctx = self.cfg, self.service.context
        if cfg.retrain_every or cfg.retrain_cron:
            self.scheduler = RetrainScheduler(cfg.schedule(), ctx.data_dir, lambda: ctx.catalog.count(split="train"),
                                              on_promoted=self._promoted, on_finished=self._finished)
            self.scheduler.start()
        if cfg.dashboard_port >= 0:
            # One champion in memory, loaded once per promotion: the planner's scorer when it has one (it is
            # thread-safe; the dashboard only reads its ensemble), else one of our own.
            planner_scorer = getattr(self.service.planner, "scorer", None)
            self.scorer = planner_scorer if isinstance(planner_scorer, ChampionScorer) \
                else ChampionScorer(ctx.data_dir, threads=cfg.scoring_threads)
            sources = DataSources(ctx.data_dir, workers=lambda: [{"id": w} for w in self.service.workers()],
                                  metrics_text=self.service.metrics.render,
                                  frames_png=FramesSource(self.scorer, ctx.catalog),
                                  retrains=self._retrains)
            config = cfg.dashboard_config()
            dashboard = Dashboard(config, sources.sources())
            try:
                dashboard.start()
            except OSError as exc:  # (the bare "[Errno 98] Address already in use" named neither port nor flag)
                raise OSError(exc.errno, f"cannot serve the dashboard on {config.host}:{config.port}: "
                                         f"{exc.strerror} (--dashboard-port P for another port, -1 for none)") from exc
            self.dashboard = dashboard

    def stop(self) -> None:
        if self.dashboard is not None:
            self.dashboard.stop()
        if self.scheduler is not None:
            self.scheduler.stop(kill_running=True)

    def _retrains(self) -> list[dict]:
        return [r.to_json() for r in self.scheduler.history] if self.scheduler else []

    def _promoted(self, version: str) -> None:
        log.info("retrain promoted %s; the scorer swaps to it on its next call", version)
        self.service.publish(EventKind.MODEL_PROMOTED, {"version": version})

    def _finished(self, record: RetrainRecord) -> None:
        status = record.status.value
        self.service.metrics.retrain(retrain_outcome(status))
        if status != "promoted":
            log.info("retrain ended %s: %s", status, record.reason)
