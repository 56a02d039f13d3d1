"""The summary of a ``bench loop`` run, from the points its arms wrote: the comparison, the plot, and the rebuild
of a run that could not summarise itself (``bench loop-summary DIR``).

Torch-free: a summary is rebuilt without the model's libraries. ``orchestrator.loopbench`` runs the arms and
calls ``summary`` when they end or are stopped; a run killed outright (SIGKILL, the machine lost) leaves its
configuration (``CONFIG``, written when it starts) and each arm's points (``ARM_POINTS``, rewritten after each
retrain), from which ``rebuild`` writes the same summary, marked ``rebuilt``.

Headline: the episodes the uniform arm needs to reach the active arm's final eval
error, divided by the active arm's budget, interpolated on the mean curves, with the per-seed values
(< 1: uniform reached active's final error with fewer episodes; None: not within the budget,
i.e. active ended ahead), and the same the other way round.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.figure import Figure

from storage.files import write_bytes_atomic
from storage.jsonsafe import finite_json

ARMS = ("active", "uniform")
#: Where an arm leaves its points for ``run_bench``, rewritten after each retrain (in the arm's data directory).
ARM_POINTS = "points.json"
#: The run's configuration, written in its output directory when it starts (``write_config``).
CONFIG = "config.json"
#: The summary, written when the run ends or is stopped, or by ``rebuild``.
SUMMARY = "summary.json"
#: The plot, written with the summary.
PLOT = "loop.png"
TRANSPORT = "in-process collection (no Zenoh); real queue, catalog, trainer and gate"


class SummaryError(ValueError):
    """A directory ``rebuild`` cannot summarise (no finished round, a damaged file); the message says why."""


def episodes_to_reach(curve: Sequence[tuple[int, float]], target: float) -> float:
    """First episode count at which a (episodes, error) curve reaches ``target`` (linear
    interpolation between points); ``inf`` when it never does."""
    prev = None
    for x, y in curve:
        if y <= target:
            if prev is None or prev[1] == y:
                return float(x)
            (x0, y0) = prev
            return float(x0 + (x - x0) * (y0 - target) / (y0 - y))
        prev = (x, y)
    return math.inf


def comparable(points: list[dict]) -> list[dict]:
    """The points at the episode counts that both arms of their seed reached: all of a finished run's (the arms
    retrain at the same counts), the rounds both arms finished of a stopped run's."""
    arms: dict[tuple[int, int], set[str]] = {}
    for p in points:
        arms.setdefault((p["seed"], p["episodes"]), set()).add(p["arm"])
    return [p for p in points if arms[(p["seed"], p["episodes"])] == set(ARMS)]


def summarize(points: list[dict], seeds: Sequence[int], metric: str = "h1_mse") -> dict:
    """Mean and spread per arm and episode count, and the headline ratios (per seed and on the means), over the
    ``comparable`` points; the headline is None when there are none (a run stopped before both arms of a seed
    finished a round)."""
    points = comparable(points)
    curves: dict[str, dict] = {}
    for arm in ARMS:
        by_ep: dict[int, list[float]] = {}
        for p in points:
            if p["arm"] == arm:
                by_ep.setdefault(p["episodes"], []).append(float(p[metric]))
        curves[arm] = {str(e): {"mean": float(np.mean(v)), "std": float(np.std(v)), "n": len(v)}
                       for e, v in sorted(by_ep.items())}
    mean = {arm: [(int(e), s["mean"]) for e, s in curves[arm].items()] for arm in ARMS}
    per_seed = []
    for seed in seeds:
        c = {arm: [(p["episodes"], float(p[metric])) for p in points if p["arm"] == arm and p["seed"] == seed]
             for arm in ARMS}
        if all(c.values()):
            per_seed.append(_ratios(c["active"], c["uniform"]) | {"seed": seed})
    headline = _ratios(mean["active"], mean["uniform"]) if points else None
    return {"metric": metric, "curves": curves, "headline": headline, "per_seed": per_seed, "paired": _paired(per_seed)}


def _paired(per_seed: list[dict]) -> dict:
    """Each seed's final error of the active arm over the uniform arm's, less 1 (negative: active ahead), with
    their mean and spread and how many seeds have active behind: the comparison BENCHMARKS.md quotes."""
    diffs = [r["active_final"] / r["uniform_final"] - 1 for r in per_seed]
    finite = [d for d in diffs if math.isfinite(d)]
    return {"per_seed": diffs, "mean": float(np.mean(finite)) if finite else None,
            "std": float(np.std(finite)) if finite else None, "active_behind": sum(d > 0 for d in finite),
            "seeds": len(finite)}


def _ratios(active: list[tuple[int, float]], uniform: list[tuple[int, float]]) -> dict:
    """uniform_needed / budget to match active's final error, and active_needed / budget for uniform's."""
    a_final, u_final = active[-1][1], uniform[-1][1]
    budget = active[-1][0]
    u_need = episodes_to_reach(uniform, a_final)
    a_need = episodes_to_reach(active, u_final)
    finite = lambda v: v if math.isfinite(v) else None  # noqa: E731 (None: not reached within the budget)
    return {"active_final": a_final, "uniform_final": u_final,
            "uniform_episodes_to_match_active": finite(u_need), "active_episodes_to_match_uniform": finite(a_need),
            "uniform_over_active_ratio": u_need / budget if math.isfinite(u_need) else None,
            "active_over_uniform_ratio": a_need / budget if math.isfinite(a_need) else None,
            "budget": budget}


def plot(points: list[dict], path: Path) -> None:
    """Mean +- std eval MSE (h1 and h5) per episodes collected, both arms (``figure``), to ``path``."""
    figure(points).savefig(path, dpi=100, bbox_inches="tight")


def figure(points: list[dict]) -> Figure:
    """The plot of ``comparable`` points only, as the headline: a stopped run's arms at the counts both reached
    (every point used to be drawn, so each x could average another set of seeds than its other arm's)."""
    drawn = comparable(points)
    empty = "no finite values" if drawn or not points else "no episode count that both arms reached yet"
    points = drawn
    fig = Figure(figsize=(10, 3.8))
    for i, metric in enumerate(("h1_mse", "h5_mse")):
        ax = fig.add_subplot(1, 2, i + 1)
        for arm, color in zip(ARMS, ("#c62828", "#1565c0")):
            by_ep: dict[int, list[float]] = {}
            for p in points:
                if p["arm"] == arm and p[metric] is not None and math.isfinite(p[metric]):
                    by_ep.setdefault(p["episodes"], []).append(p[metric])
            if not by_ep:  # e.g. h5 of episodes shorter than the context plus the longest eval horizon
                continue
            xs = sorted(by_ep)
            mu = np.array([np.mean(by_ep[x]) for x in xs])
            sd = np.array([np.std(by_ep[x]) for x in xs])
            seeds = sorted({len(by_ep[x]) for x in xs})
            ax.plot(xs, mu, "o-", color=color, label=f"{arm} (mean of {seeds[0]} seeds)" if len(seeds) == 1 else
                    f"{arm} (mean of {seeds[0]} to {seeds[-1]} seeds per point)")
            ax.fill_between(xs, mu - sd, mu + sd, color=color, alpha=0.15)
        ax.set_xlabel("training episodes collected")
        ax.set_ylabel(f"eval {metric.replace('_', ' ')}")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, empty, ha="center", va="center", transform=ax.transAxes)
    fig.suptitle("activecollect bench loop: active vs uniform planner")
    return fig


def write_summary(summary: dict, out_dir: Path) -> None:
    """``loop.png`` (its path added to ``summary``), then ``summary.json``, in ``out_dir``."""
    plot(summary["points"], out_dir / PLOT)
    summary["plot"] = str(out_dir / PLOT)
    # (h5 of episodes too short for it is NaN: null, so that strict parsers read the file)
    write_bytes_atomic(out_dir / SUMMARY,
                       json.dumps(finite_json(summary), indent=2, default=str, allow_nan=False).encode())




def arm_dir(out_dir: Path, seed: int, arm: str) -> Path:
    """An arm's data directory (catalog, queue, models, ``ARM_POINTS``) in a run's output directory."""
    return Path(out_dir) / f"seed{seed}" / arm


def summary(config: dict, seeds: Sequence[int], points: list[dict], *, interrupted: bool,
            stopped_by: str | None = None, failure: str | None = None, seconds: float | None = None,
            jobs: int | None = None, threads: int | None = None) -> dict:
    """What ``summary.json`` holds: the configuration, every point, the comparison of h1 and h5 (``summarize``),
    and how the run ended (``interrupted``, by which signal, or the failure's message)."""
    return {"config": config, "points": points, "h1": summarize(points, seeds, "h1_mse"),
            "h5": summarize(points, seeds, "h5_mse"), "seconds": seconds, "jobs": jobs, "threads": threads,
            "interrupted": interrupted, "stopped_by": stopped_by, "failure": failure, "transport": TRANSPORT}


def write_config(out_dir: Path, config: dict, jobs: int, threads: int | None) -> None:
    """``CONFIG`` in ``out_dir``, written when a run starts: what ``rebuild`` needs if the run is killed."""
    write_bytes_atomic(Path(out_dir) / CONFIG,
                       json.dumps({"config": config, "jobs": jobs, "threads": threads}, indent=2).encode())


def read_points(out_dir: Path, seeds: Sequence[int]) -> list[dict]:
    """Every point the arms of ``seeds`` wrote, seed by seed, the active arm's first. SummaryError for a file that
    is not an arm's points."""
    points = []
    for seed in seeds:
        for arm in ARMS:
            path = arm_dir(out_dir, seed, arm) / ARM_POINTS
            if path.exists():
                points += _arm_points(path, seed, arm)
    return points


def _arm_points(path: Path, seed: int, arm: str) -> list[dict]:
    got = _read_json(path)
    fields = {"arm": arm, "seed": seed}
    if not isinstance(got, list) or not all(
            isinstance(p, dict) and all(p.get(k) == v for k, v in fields.items())
            and isinstance(p.get("episodes"), int) and all(_number(p.get(k)) for k in ("h1_mse", "h5_mse"))
            for p in got):
        raise SummaryError(f"{path}: not the points of the {arm} arm of seed {seed} (a list of retrains with their "
                           "arm, seed, episodes, and h1_mse and h5_mse as numbers)")
    return got


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)  # (NaN too: h5 of short episodes)


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_bytes())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SummaryError(f"{path}: not JSON ({exc})") from None
    except OSError as exc:  # (a folder of that name, a file it may not read: not a raw errno line)
        raise SummaryError(f"{path}: cannot read it ({exc.strerror})") from None


def rebuild(out_dir: Path) -> dict:
    """``summary.json`` and ``loop.png`` of a run that did not write them (killed outright, or still running),
    from its ``CONFIG`` and its arms' points; returns the summary, marked ``rebuilt``, ``interrupted`` unless
    every arm reached the budget (``seconds`` and ``stopped_by`` are not known: None).

    SummaryError when ``out_dir`` has no ``CONFIG`` or no finished round, when a file is damaged, or when the run
    summarised itself (that summary is kept: it knows how the run ended and how long it took).
    """
    out_dir = Path(out_dir)
    for name in (PLOT, SUMMARY):  # (before anything is written: a raw errno line, once loop.png was written)
        if (out_dir / name).is_dir():
            raise SummaryError(f"cannot write {out_dir / name}: a directory is in its place (move it away)")
    path = out_dir / CONFIG
    if not path.is_file():
        raise SummaryError(f"{out_dir} holds no {CONFIG}: not the output directory of a bench loop run")
    run = _read_json(path)
    try:
        config = run["config"]  # type: ignore[index]
        seeds, budget = [int(s) for s in config["seeds"]], int(config["budget"])
    except (KeyError, TypeError, ValueError) as exc:
        raise SummaryError(f"{path}: not a bench loop configuration ({type(exc).__name__}: {exc})") from None
    if (out_dir / SUMMARY).exists():
        try:
            old = _read_json(out_dir / SUMMARY)
        except SummaryError:
            old = None  # (damaged: rebuilt from the points)
        if isinstance(old, dict) and not old.get("rebuilt"):
            raise SummaryError(f"{out_dir / SUMMARY} was written by the run itself; it is kept")
    points = read_points(out_dir, seeds)
    if not points:
        raise SummaryError(f"no round had finished in {out_dir}: nothing to summarise")
    last = {(p["seed"], p["arm"]): p["episodes"] for p in points}
    finished = all(last.get((seed, arm)) == budget for seed in seeds for arm in ARMS)
    out = summary(config, seeds, points, interrupted=not finished, jobs=run.get("jobs"),
                  threads=run.get("threads")) | {"rebuilt": True}
    try:
        write_summary(out, out_dir)
    except OSError as exc:
        raise SummaryError(f"cannot write {exc.filename or out_dir}: {exc.strerror or exc}") from None
    return out
