"""``activecollect bench loop``: the active planner against the uniform planner.

Both arms get the same seed, the same episode budget, the same policy mix, the
same eval split and the same training schedule (retrain from scratch every
``round_episodes`` episodes, synchronously, so each arm's k-th model has seen
exactly k rounds). The first round is the same uniform seed requests in both arms;
after that the active arm plans from its champion's disagreement on the last
round's episodes, the uniform arm draws uniformly.

Collection runs in-process through a ``Collect`` callable (the CLI passes the
simulator's ``collect_episode``), not over Zenoh: the question here is which
planner yields the better data per episode, and with a deterministic simulator
the transport does not change what is collected; leaving it out removes timing
from the comparison (with asynchronous workers, how many episodes arrive while a
retrain runs would differ between arms). The queue, catalog, registry, trainer
and gate are the real ones.

The comparison is configured by ``orchestrator.loopconfig.LoopBenchConfig`` (torch-free,
for the CLI's parser). The active arm ranks steps by its ``signal`` (see
``loopconfig.SIGNALS``); episodes are stored under ids that sort in collection order
(``_bench_id``), so training reads them in the same order in every run and two runs
of one configuration give the same numbers.

The summary, its headline and the plot are ``orchestrator.loopsummary``'s.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import signal
import sys
import time
import zlib
from multiprocessing import connection as mp_connection
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from orchestrator.champion import ChampionScorer, limit_torch_threads, make_torch_deterministic
from orchestrator.loopconfig import HEAD_SIGNALS, LoopBenchConfig
from orchestrator.loopsummary import (ARM_POINTS, ARMS, arm_dir, read_points, summary as make_summary,
                                      write_config, write_summary)
from orchestrator.planner import ActivePlanner, Planner, Scores, in_eval_split
from orchestrator.uniform import UniformPlanner
from orchestrator.retrain import run_retrain
from orchestrator.retrainjob import die_with_parent
from orchestrator.signals import Terminated, sigterm_raises
from storage.catalog import Catalog
from storage.files import write_bytes_atomic
from storage.queue import RequestQueue
from storage.requests import Request
from storage.records import Episode
from uncertainty.config import TrainConfig
from uncertainty.score import (change_disagreement, colour_disagreement, object_moving, prediction_error,
                               predicted_variance)
from workers.env import MARKER_RGB, OBJECT_RGB, SHAPE_PALETTE, scene_colours

#: Object colour per shape (``workers.env.SHAPE_PALETTE``), or None: every object in ``OBJECT_RGB``.
Palette = Mapping[str, tuple[int, int, int]] | None
#: Collects the episode a request asks for: (request, policy seed, image size, palette) -> Episode.
Collect = Callable[[Request, int, int, Palette], Episode]
#: Creates (or checks) the pinned eval split in a catalog: (catalog, episodes, seed, steps, image size,
#: random physics, palette) -> hash.
MakeEvalSplit = Callable[[Catalog, int, int, int, int, bool, Palette], str]
#: Seconds a stopped arm's process has to exit before it is killed.
ARM_EXIT_S = 10.0
#: The ``object_pixels`` signal's object (body and marker); the rest of a frame is ``workers.env.scene_colours``
#: of its size (the walls' anti-aliased edges differ with it, and some are nearer the object's blue than grey).
OBJECT_COLOURS = (OBJECT_RGB, MARKER_RGB)


def palette_of(cfg: LoopBenchConfig) -> Palette:
    """The objects' colours of ``cfg.palette``: None (all alike) or one per shape."""
    return dict(SHAPE_PALETTE) if cfg.palette == "per-shape" else None


def object_colours(palette: Palette) -> tuple[tuple[int, int, int], ...]:
    """The ``object_pixels`` signal's colours in a world of ``palette``."""
    return OBJECT_COLOURS if palette is None else tuple(dict.fromkeys((*palette.values(), MARKER_RGB)))


class SignalScorer:
    """The champion's ``Scores`` by the bench's signal (``ChampionScorer`` loads and hot-swaps it)."""

    def __init__(self, champion: ChampionScorer, signal: str, horizon: int,
                 colours: Sequence[tuple[int, int, int]] = OBJECT_COLOURS) -> None:
        self.champion = champion
        self.signal = signal
        self.horizon = horizon
        self.colours = tuple(colours)

    def __call__(self, episode: Episode) -> Scores | None:
        if self.signal == "disagreement" and self.horizon == 1:
            return self.champion(episode)
        self.champion.reload()
        ensemble, version = self.champion.ensemble, self.champion.version
        if ensemble is None or version is None:
            return None
        if self.signal in ("disagreement", "random"):
            per_step = ensemble.disagreement(episode.frames, episode.actions, horizon=self.horizon)
            if self.signal == "random":  # the same steps, at random (seeded by the episode's id: alike in every run)
                rng = np.random.default_rng(zlib.crc32(episode.meta.episode_id.encode()))
                per_step = np.where(np.isnan(per_step), np.nan, rng.random(len(per_step)))
        elif self.signal == "error":
            per_step = prediction_error(ensemble, episode.frames, episode.actions, horizon=self.horizon)
        elif self.signal in HEAD_SIGNALS:
            per_step = predicted_variance(ensemble, episode.frames, episode.actions, total=self.signal == "total")
        elif self.signal == "object_pixels":
            per_step = colour_disagreement(ensemble, episode.frames, episode.actions, self.colours,
                                           scene_colours(episode.frames.shape[1]), horizon=self.horizon)
        else:
            per_step = change_disagreement(ensemble, episode.frames, episode.actions, horizon=self.horizon)
        if self.signal == "object":
            per_step = np.where(object_moving(episode.states, self.horizon), per_step, np.nan)
        return self.champion.scores(episode, per_step, ensemble, version)


def make_planner(arm: str, cfg: LoopBenchConfig, scorer: ChampionScorer, rng: np.random.Generator,
                 catalog: Catalog, queue: RequestQueue) -> Planner:
    depth = lambda: queue.counts().get("queued", 0)  # noqa: E731
    if arm == "active":
        colours = object_colours(palette_of(cfg))
        return ActivePlanner(cfg.active, SignalScorer(scorer, cfg.signal, cfg.signal_horizon, colours), rng, depth,
                             is_eval=in_eval_split(catalog))
    if arm == "uniform":
        return UniformPlanner(cfg.uniform_config(), rng, depth)
    raise ValueError(f"arm must be one of {ARMS}, found {arm!r}")


def run_arm(arm: str, seed: int, cfg: LoopBenchConfig, data_dir: Path, collect: Collect,
            make_eval_split: MakeEvalSplit, log: Callable[[str], None] = print) -> list[dict]:
    """One arm for one seed; returns one point per retrain (episodes, h1/h5 of candidate and champion). The points
    so far are also in ``data_dir/ARM_POINTS`` after each retrain (written atomically): a stopped run keeps them."""
    catalog = Catalog(data_dir)
    queue = RequestQueue(catalog.db_path)
    palette = palette_of(cfg)
    make_eval_split(catalog, cfg.eval_episodes, cfg.eval_seed, cfg.steps, cfg.image_size, cfg.random_physics,
                    palette)
    scorer = ChampionScorer(data_dir, with_error=cfg.active.shapes_by_progress,
                            error_horizon=cfg.active.progress_horizon)
    planner = make_planner(arm, cfg, scorer, np.random.default_rng(seed), catalog, queue)
    train = TrainConfig(**{**cfg.train.to_dict(), "seed": seed, "widths": tuple(cfg.train.widths)})
    points: list[dict] = []
    round_eps: list[Episode] = []
    round_requests: list[Request] = []
    collected = catalog.count(split="train")
    while collected < cfg.budget:
        missing = cfg.round_episodes - len(round_eps) - queue.counts().get("queued", 0)
        if missing > 0:  # the first round, or a round the planner could not fill with diverse states
            queue.enqueue_many(planner.seed(missing))
        lease = queue.lease("bench", (), (), 600.0)
        ep = _bench_id(collect(lease.request, seed * 1_000_003 + collected, cfg.image_size, palette), seed,
                       collected)
        stored = catalog.add_episode(ep)
        queue.complete(lease.request.id, lease.token, stored.episode_id)
        round_eps.append(ep)
        round_requests.append(lease.request)
        collected += 1
        if len(round_eps) == cfg.round_episodes or collected == cfg.budget:
            planner.observe(round_eps)  # before the retrain that trains on them
            start = time.perf_counter()
            result = run_retrain(data_dir, train)
            points.append(_point(arm, seed, collected, result, time.perf_counter() - start, round_requests))
            rho = points[-1]["spearman"]
            log(f"  {arm:7s} seed {seed} {collected:4d} ep: h1 {points[-1]['h1_mse']:.3e} "
                f"h5 {points[-1]['h5_mse']:.3e} spearman {float('nan') if rho is None else rho:.2f} "
                f"({points[-1]['train_s']:.0f} s)")
            # (NaN, an h5 of episodes too short for it, reads back as NaN)
            write_bytes_atomic(data_dir / ARM_POINTS, json.dumps(points).encode())
            queue.enqueue_many(planner.plan(round_eps))
            round_eps, round_requests = [], []
    queue.close()
    return points


def _bench_id(ep: Episode, seed: int, index: int) -> Episode:
    """The episode under an id that sorts in collection order and is the same in every run.

    Training reads the snapshot in id order; with uuid4 ids the order, and with it the
    batches, changed from run to run (~1-2% eval noise between identical runs).
    """
    meta = dataclasses.replace(ep.meta, episode_id=f"bench{seed:04d}n{index:06d}")
    return dataclasses.replace(ep, meta=meta)


def _point(arm: str, seed: int, episodes: int, result: dict, seconds: float, requests: list[Request]) -> dict:
    """One retrain's figures (eval h1/h5 MSE, and how well its disagreement ranks the eval error: ``spearman``),
    with how many of the round's requests came from each planner, policy and shape."""
    def counts(values: list[str]) -> dict[str, int]:
        return {k: values.count(k) for k in sorted(set(values))}
    m = result["metrics"]
    return {"arm": arm, "seed": seed, "episodes": episodes, "version": result["version"],
            "h1_mse": m.get("h1_mse"), "h5_mse": m.get("h5_mse"), "spearman": m.get("spearman"),
            "promoted": result["promoted"],
            "champion": result["champion"], "train_s": round(seconds, 1),
            "round_planners": counts([str(r.reason.get("planner", "")) for r in requests]),
            "round_policies": counts([r.policy for r in requests]),
            "round_shapes": counts([r.shape for r in requests])}


def run_bench(cfg: LoopBenchConfig, out_dir: Path, collect: Collect, make_eval_split: MakeEvalSplit,
              log: Callable[[str], None] = print, jobs: int = 1, threads: int = 0) -> dict:
    """Every seed, both arms; writes ``summary.json`` and ``loop.png`` in ``out_dir``; returns the summary. The
    configuration goes to ``out_dir/config.json`` first, so that a run killed outright (no chance to summarise)
    can be summarised from its arms' points afterwards (``loopsummary.rebuild``, ``bench loop-summary``).

    Stopped by Ctrl-C or SIGTERM (a timeout's, a supervisor's), it stops the arms and summarises the rounds they
    had finished: ``interrupted`` true and ``stopped_by`` the signal's name in the summary, the comparison over
    the rounds both arms of a seed finished (``comparable``); nothing is written when no round had finished.

    ``jobs`` > 1 runs each (seed, arm) in a process of its own, that many at once (``_run_apart``; their
    progress lines go to stderr, not to ``log``);
    ``threads``: torch threads per arm (0: torch's own with one job, the usable cores shared out
    with more). The arms share nothing but the machine, so on the CPU the figures are the same
    as one after the other at the same ``threads``. ArmFailed when an arm's process fails, once the others are
    stopped and the rounds they had finished summarised as a stopped run's (``stopped_by`` "failure"; the
    exception's ``summary``).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = [(seed, arm, arm_dir(out_dir, seed, arm)) for seed in cfg.seeds for arm in ARMS]
    for _, _, data_dir in runs:
        if (data_dir / "catalog.sqlite").exists():
            raise ValueError(f"{data_dir} already holds a catalog; give bench loop a fresh --out")
    if jobs > 1 and not threads:
        threads = max(1, len(os.sched_getaffinity(0)) // min(jobs, len(runs)))
    write_config(out_dir, cfg.to_json(), jobs, threads or None)  # (what `bench loop-summary` needs if killed)
    start = time.perf_counter()
    stopped_by, failure = None, None
    try:
        with sigterm_raises():
            if jobs > 1:
                _run_apart(runs, cfg, collect, make_eval_split, jobs, threads)
            else:
                limit_torch_threads(threads)
                if cfg.deterministic:
                    make_torch_deterministic()
                for seed, arm, data_dir in runs:
                    run_arm(arm, seed, cfg, data_dir, collect, make_eval_split, log)
    except (KeyboardInterrupt, Terminated) as exc:
        stopped_by = "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"
    except ArmFailed as exc:
        stopped_by, failure = "failure", exc
    points = read_points(out_dir, cfg.seeds)
    summary = make_summary(cfg.to_json(), cfg.seeds, points, interrupted=stopped_by is not None,
                           stopped_by=stopped_by, failure=None if failure is None else str(failure),
                           seconds=round(time.perf_counter() - start, 1), jobs=jobs, threads=threads or None)
    if points:  # (stopped before any round: nothing measured, nothing written)
        write_summary(summary, out_dir)
    if failure is not None:
        failure.summary = summary if points else None
        raise failure
    return summary


class ArmFailed(RuntimeError):
    """An arm's process of a ``run_bench`` with ``jobs`` > 1 ended without its figures (its error went to stderr).
    ``summary``: the run's, of the rounds finished before (written to summary.json), or None when there were none."""

    summary: dict | None = None


def _run_apart(runs: list[tuple[int, str, Path]], cfg: LoopBenchConfig, collect: Collect,
               make_eval_split: MakeEvalSplit, jobs: int, threads: int) -> None:
    """Each (seed, arm, data directory) in a process of its own, ``jobs`` at a time; each leaves its points in its
    directory's ARM_POINTS.

    The processes are spawned, not forked (torch's threads and CUDA do not survive a fork), so ``collect``
    and ``make_eval_split`` must be module-level functions. The first arm that fails stops the others
    (terminated, not waited for) and raises ArmFailed.
    """
    ctx = multiprocessing.get_context("spawn")
    pending = list(runs)
    running: dict[int, tuple[multiprocessing.process.BaseProcess, int, str]] = {}
    try:
        while pending or running:
            while pending and len(running) < jobs:
                seed, arm, data_dir = pending.pop(0)
                proc = ctx.Process(target=_arm_process, name=f"bench-loop-seed{seed}-{arm}",
                                   args=(arm, seed, cfg, data_dir, collect, make_eval_split, threads, os.getpid()))
                proc.start()
                running[proc.sentinel] = (proc, seed, arm)
            for sentinel in mp_connection.wait(list(running)):
                proc, seed, arm = running.pop(sentinel)  # type: ignore[index]
                proc.join()
                if proc.exitcode != 0:
                    raise ArmFailed(f"bench loop: the {arm} arm of seed {seed} failed (exit code {proc.exitcode}); "
                                    "its error is above")
    finally:
        for proc, _, _ in running.values():
            proc.terminate()
        for proc, _, _ in running.values():
            proc.join(ARM_EXIT_S)
            if proc.exitcode is None:  # (an arm that hangs in its exit)
                proc.kill()
                proc.join()


def _arm_process(arm: str, seed: int, cfg: LoopBenchConfig, data_dir: Path, collect: Collect,
                 make_eval_split: MakeEvalSplit, threads: int, parent: int) -> None:
    """``run_arm`` in a spawned process (which leaves its points in ``data_dir/ARM_POINTS``).

    Ctrl-C reaches the whole process group; the arms leave it to ``_run_apart``, which terminates them.
    An arm dies with ``parent`` (the ``run_bench`` that started it), however that ends: a SIGTERM or
    SIGKILL to it alone gives ``_run_apart`` no chance to terminate them, and an orphaned arm would go
    on training for minutes.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Stopped, an arm exits rather than dies: what it holds is released (tqdm's lock, a named semaphore the
    # resource tracker would otherwise report as leaked when the command ends). Not inside pymunk's callbacks,
    # where the exception would be lost or crash the arm, nor lost in another callback (see sigterm_raises).
    try:
        with sigterm_raises():
            die_with_parent()
            if os.getppid() != parent:  # it died before the line above: no signal will come
                sys.exit(1)
            limit_torch_threads(threads)
            if cfg.deterministic:  # (before the arm's first CUDA call)
                make_torch_deterministic()
            run_arm(arm, seed, cfg, data_dir, collect, make_eval_split, log_stderr)
    except Terminated:
        # An exit that hangs would leave the arm with nobody to stop it (its command SIGKILLed): an alarm ends it.
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        signal.alarm(max(1, int(ARM_EXIT_S)))
        sys.exit(128 + signal.SIGTERM)


def log_stderr(line: str) -> None:
    """A progress line to stderr, at once (the CLI's ``log``, and each arm's in its own process)."""
    print(line, file=sys.stderr, flush=True)
