"""The run report: an HTML page with PNG plots, written to ``DATA/reports/<timestamp>/``.

Plots: eval error per training episodes the model was trained on (every registered
model, the champions joined by a line), disagreement over object position (the champion's
per-step scores on training episodes, at the object's position), and predicted
versus real frames for a few eval samples. Each plot is a function returning PNG
bytes, so the dashboard can serve the same pictures.
"""

from __future__ import annotations

import html
import io
import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import matplotlib
import numpy as np
import torch
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from storage.jsonsafe import finite_json
from storage.records import STATE_COLUMN as _COL, Episode
from uncertainty.ensemble import Ensemble, episode_windows, frames_to_tensor

matplotlib.use("Agg")  # no display on servers; Figure() below never needs pyplot's global state


#: The learning curve's x axis: what each model's ``train_episodes`` metric counts.
CURVE_X_LABEL = "training episodes the model was trained on"
#: The report's names of ``activecollect run``'s summary keys whose bare name says less than they mean (summary.json
#: keeps the keys): a resumed run's ``episodes`` are the catalog's, its retrains and seconds its own.
SUMMARY_LABELS = {"planner": "planner (this run)", "episodes": "training episodes (catalog)",
                  "quarantined": "of those, quarantined (not trained on)",
                  "collected_this_run": "collected by this run", "budget": "budget (training episodes)",
                  "round_episodes": "episodes per round", "retrains": "retrains (this run)",
                  "champion_h1_mse": "champion eval h1 MSE", "seconds": "seconds (this run)",
                  "interrupted_in": "interrupted in", "champion_problem": "champion cannot be loaded"}


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    return buf.getvalue()


def curve_png(points: Sequence[dict], title: str = "Eval error per training episodes") -> bytes:
    """Eval MSE (h1, h5) of each model against the training episodes it saw, as PNG (see ``curve_figure``)."""
    return _png(curve_figure(points, title))


def curve_figure(points: Sequence[dict], title: str = "Eval error per training episodes") -> Figure:
    """Eval MSE (h1, h5) of each model against the training episodes it was trained on (not the episodes
    collected when it was made: a quarantined episode, or one of another frame size, is left out of training).

    ``points``: dicts with episodes, h1_mse, h5_mse, promoted, rolled_back, status and the copy-last baselines
    (as ``dashboard.learning_curve``; the newest baseline is drawn dashed).
    """
    fig = Figure(figsize=(8.4, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    for key, color in (("h1_mse", "#1565c0"), ("h5_mse", "#c62828")):
        pts = [p for p in points if isinstance(p.get(key), (int, float)) and np.isfinite(p[key])]
        if not pts:
            continue
        ax.scatter([p["episodes"] for p in pts], [p[key] for p in pts], color=color, alpha=0.35, s=18,
                   label=f"{key} (every candidate)")
        champs = [p for p in pts if p.get("promoted")]
        if champs:
            ax.plot([p["episodes"] for p in champs], [p[key] for p in champs], "o-", color=color,
                    label=f"{key} (promoted)")
        withdrawn = [p for p in pts if p.get("rolled_back")]
        if withdrawn:  # promoted once, then rolled back: not part of the champions' line
            ax.scatter([p["episodes"] for p in withdrawn], [p[key] for p in withdrawn], marker="x", color=color,
                       s=40, label=f"{key} (rolled back)")
        current = [p for p in pts if p.get("status") == "champion"]
        if current:
            ax.scatter([p["episodes"] for p in current], [p[key] for p in current], marker="*", s=160,
                       color=color, edgecolors="black", zorder=5, label=f"{key} (champion now)")
        base = [p[f"baseline_{key}"] for p in pts if isinstance(p.get(f"baseline_{key}"), (int, float))
                and np.isfinite(p[f"baseline_{key}"])]
        if base:  # copy-last's error on the eval split (the same for every model of one split): what to beat
            ax.axhline(base[-1], color=color, linestyle="--", linewidth=1, label=f"{key} of copy-last-frame")
    ax.set_xlabel(CURVE_X_LABEL)
    values = [y for line in ax.get_lines() for y in line.get_ydata()] + \
        [y for coll in ax.collections for _, y in coll.get_offsets()]
    if values and min(values) > 0:  # h5 is several times h1: on one linear axis h1's fall looked flat
        ax.set_yscale("log")
    ax.set_ylabel("eval MSE (log scale)" if ax.get_yscale() == "log" else "eval MSE")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if ax.has_data():
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # (beside the lines, not over them)
        fig.tight_layout()
    else:
        ax.text(0.5, 0.5, "no model evaluated yet", ha="center", transform=ax.transAxes)
    return fig


def disagreement_png(ensemble: Ensemble, episodes: Sequence[Episode]) -> bytes:
    """Per-step disagreement of ``ensemble`` scattered at the object's position on the table."""
    xs, ys, scores = [], [], []
    for ep in episodes:
        s = ensemble.disagreement(ep.frames, ep.actions)
        ok = np.isfinite(s)
        xs.append(ep.states[ok, _COL["obj_x"]])
        ys.append(ep.states[ok, _COL["obj_y"]])
        scores.append(s[ok])
    fig = Figure(figsize=(5, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    if scores and sum(len(s) for s in scores):
        c = np.concatenate(scores)
        floor = max(float(c[c > 0].min()) if (c > 0).any() else 1e-12, 1e-12)
        order = np.argsort(c)  # most uncertain drawn last, on top
        sc = ax.scatter(np.concatenate(xs)[order], np.concatenate(ys)[order], c=np.maximum(c[order], floor), s=8,
                        cmap="viridis", norm=LogNorm(vmin=floor, vmax=max(float(c.max()), floor * 10)))
        fig.colorbar(sc, ax=ax, label="ensemble disagreement (log scale)")
    ax.set_xlim(0, 512)
    ax.set_ylim(0, 512)
    ax.set_aspect("equal")
    ax.set_xlabel("object x")
    ax.set_ylabel("object y")
    ax.set_title(f"Disagreement over object position ({len(episodes)} episodes)", fontsize=10)
    return _png(fig)


@torch.inference_mode()
def frames_png(ensemble: Ensemble, episodes: Sequence[Episode], samples: int = 3, seed: int = 0) -> bytes:
    """For a few eval steps: last context frame, the real next frame, the ensemble mean, its variance."""
    rng = np.random.default_rng(seed)
    rows = []
    for ep in list(episodes)[:samples]:
        windows = episode_windows(ep.frames, ep.actions, ensemble.config, horizon=1)
        if windows is None:
            continue
        steps, ctx_idx, act_idx = windows
        i = int(rng.integers(len(steps)))
        x = frames_to_tensor(ep.frames, ensemble.device)                                # (T, 3, H, W)
        ctx = x[torch.as_tensor(ctx_idx[i:i + 1])]                                       # (1, C, 3, H, W)
        act = ensemble.normalize_actions(torch.as_tensor(ep.actions[act_idx[i, 0]][None], dtype=torch.float32,
                                                         device=ensemble.device))                # (1, A)
        preds = ensemble(ctx, act).clamp(0, 1)[:, 0]                                     # (K, 3, H, W)
        mean = preds.mean(0).permute(1, 2, 0).cpu().numpy()                              # (H, W, 3)
        var = preds.var(0, unbiased=False).mean(0).cpu().numpy()                         # (H, W)
        t = int(steps[i])
        rows.append((ep.frames[t], ep.frames[t + 1], mean, var, f"{ep.meta.shape} step {t}"))
    fig = Figure(figsize=(8, 2.1 * max(1, len(rows))))
    titles = ("context (t)", "real (t+1)", "predicted mean (t+1)", "member variance")
    vmax = max([float(r[3].max()) for r in rows] + [1e-12])  # one scale for every row, so rows compare
    for r, (ctx_f, real, mean, var, label) in enumerate(rows):
        for c, img in enumerate((ctx_f, real, mean, var)):
            ax = fig.add_subplot(len(rows), 4, r * 4 + c + 1)
            shown = ax.imshow(img, cmap="magma" if c == 3 else None, interpolation="nearest",
                              **({"vmin": 0.0, "vmax": vmax} if c == 3 else {}))
            if c == 3:
                fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.04)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c], fontsize=9)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    if not rows:
        fig.text(0.5, 0.5, "no eval episodes long enough", ha="center")
    return _png(fig)


@dataclass
class ReportInputs:
    """What a report shows."""

    curve: list[dict]
    """Learning-curve points (``dashboard.learning_curve``)."""
    summary: dict[str, Any]
    """Headline numbers of the run (episodes, champion, eval error, time, settings)."""
    retrains: list[dict] = field(default_factory=list)
    """``RetrainRecord.to_json()`` of each retrain."""
    champion: Ensemble | None = None
    """The champion ensemble (None before the first promotion)."""
    train_sample: list[Episode] = field(default_factory=list)
    """Training episodes for the disagreement map."""
    eval_sample: list[Episode] = field(default_factory=list)
    """Eval episodes for predicted vs real frames."""


def write_report(data_dir: Path, inputs: ReportInputs, when: float | None = None) -> Path:
    """Write ``DATA/reports/<timestamp>/index.html`` with its PNGs; returns the index path.

    The files are written in a hidden sibling folder (``.<timestamp>-<pid>.tmp``) renamed into place
    once whole, so a report cut short leaves no ``<timestamp>/`` folder without its page: one that
    raises removes what it wrote, one killed leaves only the hidden folder, which the next report deletes (the
    caller holds the data directory: ``run`` holds its service lock while it writes).
    """
    reports = Path(data_dir) / "reports"
    stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(when or time.time()))
    reports.mkdir(parents=True, exist_ok=True)
    for left in reports.glob(".*.tmp"):  # what killed writers left: only run writes here, holding the directory
        shutil.rmtree(left, ignore_errors=True)
    tmp = reports / f".{stamp}-{os.getpid()}.tmp"
    tmp.mkdir()
    try:
        _write_files(tmp, inputs)
        return _rename_into_place(tmp, reports, stamp) / "index.html"
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_files(out: Path, inputs: ReportInputs) -> None:
    images = {"curve.png": curve_png(inputs.curve)}
    if inputs.champion is not None:
        images["disagreement.png"] = disagreement_png(inputs.champion, inputs.train_sample)
        images["frames.png"] = frames_png(inputs.champion, inputs.eval_sample)
    for name, data in images.items():
        (out / name).write_bytes(data)
    summary = {"summary": inputs.summary, "curve": inputs.curve, "retrains": inputs.retrains}
    (out / "summary.json").write_text(json.dumps(finite_json(summary), indent=2, default=str, allow_nan=False))
    (out / "index.html").write_text(_html(inputs, images))


def _rename_into_place(tmp: Path, reports: Path, stamp: str) -> Path:
    """``tmp`` renamed to ``reports/<stamp>`` (``<stamp>-N`` when that is taken); the folder it now is."""
    n = 0
    while True:
        out = reports / (f"{stamp}-{n}" if n else stamp)
        if not out.exists():
            try:
                tmp.rename(out)
                return out
            except OSError:  # (made by another writer since the look: the next name)
                if not out.exists():
                    raise
        n += 1


def _html(inputs: ReportInputs, images: dict[str, bytes]) -> str:
    esc = html.escape
    summary = "".join(f"<tr><th>{esc(SUMMARY_LABELS.get(str(k), str(k)))}</th><td>{esc(_fmt(v))}</td></tr>"
                      for k, v in inputs.summary.items())
    retrain_rows = "".join(
        f"<tr><td>{esc(r.get('trigger', ''))}</td><td>{r.get('episodes', '')}</td><td>{esc(str(r.get('status')))}"
        f"</td><td>{esc(r.get('version') or '')}</td><td>{esc(_fmt(r.get('metrics', {}).get('h1_mse')))}</td>"
        f"<td>{esc(_fmt((r.get('finished') or 0) - r.get('started', 0)))}</td>"
        f"<td>{esc(r.get('reason') or '')}</td></tr>"
        for r in inputs.retrains)
    figs = {"curve.png": f"Eval error per {CURVE_X_LABEL}",
            "disagreement.png": "Champion disagreement over object position (each step of the newest training "
                                "episodes, at its object's position on the table; world units, y up)",
            "frames.png": "Predicted versus real frames (champion, eval episodes)"}
    body = "".join(f"<h2>{esc(title)}</h2><img src='{name}' alt='{esc(title)}'>"
                   for name, title in figs.items() if name in images)
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>activecollect run report</title>
<style>body{{font:14px/1.4 system-ui,sans-serif;margin:2em;max-width:60em}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:left}}
img{{max-width:100%;border:1px solid #ddd}}</style></head><body>
<h1>activecollect run report</h1>
{"".join(f"<p>{esc(line)}</p>" for line in _headline(inputs.summary, inputs.retrains))}
<table>{summary}</table>
{body}
<h2>Retrains</h2>
<table><tr><th>trigger</th><th>episodes</th><th>status</th><th>version</th><th>h1 MSE</th><th>seconds</th>
<th>reason</th></tr>{retrain_rows}</table>
</body></html>
"""


#: What an interrupted run had left to do, by its summary's ``interrupted_in``.
INTERRUPTED_IN = {"set-up": " during set-up", "collection": " before the budget was spent",
                  "the last retrain": " with the budget spent, before its last retrain"}


def _headline(summary: dict[str, Any], retrains: Sequence[dict]) -> list[str]:
    """What a reader must know before the numbers: a run stopped early, one that resumed an earlier run's
    catalog, one that has no champion to show or whose champion none of its retrains made."""
    lines = []
    if summary.get("interrupted"):
        where = summary.get("interrupted_in")
        if where is None and isinstance(summary.get("episodes"), int) and isinstance(summary.get("budget"), int):
            where = "collection" if summary["episodes"] < summary["budget"] else None  # (a summary from before it)
        lines.append(f"Interrupted (Ctrl-C or SIGTERM){INTERRUPTED_IN.get(where, '')}: "
                     "the next run on this data directory resumes from its catalog.")
    collected, episodes = summary.get("collected_this_run"), summary.get("episodes")
    if isinstance(collected, int) and isinstance(episodes, int) and collected != episodes:
        lines.append(f"This run collected {collected} of the catalog's {episodes} training episodes; the rest "
                     "came before it. Its retrains, time and planner are its own; the learning curve shows "
                     "every model of the data directory.")
    failed = [r for r in retrains  # (a job killed after its gate keeps its version: it made a model)
              if r.get("status") not in ("promoted", "rejected", "busy", "running") and not r.get("version")]
    if retrains and len(failed) == len(retrains):
        lines.append(f"Every one of this run's {len(retrains)} retrains ended without a model ("
                     f"{', '.join(sorted({str(r.get('status')) for r in failed}))}; see below): nothing was gated.")
    if "champion" in summary and not summary["champion"]:
        lines.append("No champion: no candidate has passed the promotion gate yet (see the retrains below); "
                     "the disagreement map and the predicted-vs-real frames need one.")
    elif summary.get("champion_problem"):
        lines.append(f"The champion, {summary['champion']}, cannot be loaded, so the disagreement map and the "
                     f"predicted-vs-real frames are left out: {summary['champion_problem']}")
    elif retrains and not any(r.get("status") == "promoted" for r in retrains):
        lines.append(f"None of this run's {len(retrains)} retrains was promoted (see below): the champion, "
                     f"{summary.get('champion')}, is a model made before them.")
    return lines


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):  # e.g. the queue's counts: queued=0 leased=0 ...
        return " ".join(f"{k}={_fmt(x)}" for k, x in v.items())
    return "" if v is None else str(v)
