"""Where does the champion's error come from, and does disagreement see it? (BENCHMARKS.md, calibration)

For every horizon-1 window of the pinned eval split of a data directory, with the champion (or a
given version): the members' variance (disagreement), the ensemble mean's error, and the
copy-last error (how much the frame changes), each also split into changing and static pixels
(a pixel changes when the true or the predicted next frame differs from the last by > 2 %).
Prints the Spearman correlations between them. Inference only.

    .venv/bin/python bench/calibration_diagnostic.py --data DIR [--version V]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from orchestrator.cli.common import Parser
from storage.catalog import Catalog
from storage.database import DB_NAME
from storage.models import ModelRegistry
from uncertainty import metrics as M
from uncertainty.checkpoint import load_ensemble
from uncertainty.train import build_windows, load_eval

#: A pixel "changes" when some channel moves by more than this (frames in [0, 1]).
CHANGE = 0.02


def diagnose(data: Path, version: str | None = None, batch: int = 64) -> dict:
    if not (data / DB_NAME).is_file():
        raise SystemExit(f"{data}: not a data directory (no {DB_NAME})")
    catalog, registry = Catalog(data), ModelRegistry(data)
    version = version or registry.champion()
    if version is None:
        raise SystemExit(f"{data}: no champion and no --version")
    ens = load_ensemble(registry, version)
    episodes, _ = load_eval(catalog)
    windows = build_windows(episodes, ens.config, horizon=1)
    names = ("var", "var_moving", "var_static", "err", "err_static", "base")
    cols: dict[str, list[torch.Tensor]] = {k: [] for k in names}
    with torch.inference_mode():
        for lo in range(0, len(windows), batch):
            ctx, act, tgt = windows.batch(torch.arange(lo, min(lo + batch, len(windows))), ens.device)
            preds = ens.rollout(ctx, ens.normalize_actions(act))[:, :, 0]     # (K, B, 3, H, W)
            last, true = ctx[:, -1], tgt[:, 0]                                   # (B, 3, H, W)
            mean = preds.mean(dim=0)
            moving = (((true - last).abs().amax(1, keepdim=True) > CHANGE)
                      | ((mean - last).abs().amax(1, keepdim=True) > CHANGE))  # (B, 1, H, W)
            var, err = preds.var(dim=0, unbiased=False), (mean - true) ** 2    # (B, 3, H, W)
            n = var[0].numel()
            cols["var"].append(var.mean(dim=(1, 2, 3)))
            cols["var_moving"].append((var * moving).sum(dim=(1, 2, 3)) / n)
            cols["var_static"].append((var * ~moving).sum(dim=(1, 2, 3)) / n)
            cols["err"].append(err.mean(dim=(1, 2, 3)))
            cols["err_static"].append((err * ~moving).sum(dim=(1, 2, 3)) / n)
            cols["base"].append(((last - true) ** 2).mean(dim=(1, 2, 3)))
    c = {k: torch.cat(v).double().cpu().numpy() for k, v in cols.items()}
    return {
        "version": version, "windows": int(len(c["var"])), "image_size": ens.config.image_size,
        "members": ens.members,
        "share_of_variance_on_static_pixels": float(c["var_static"].sum() / c["var"].sum()),
        "share_of_error_on_static_pixels": float(c["err_static"].sum() / c["err"].sum()),
        "spearman_disagreement_error": M.spearman(c["var"], c["err"]),
        "spearman_moving_disagreement_error": M.spearman(c["var_moving"], c["err"]),
        "spearman_copy_last_error_error": M.spearman(c["base"], c["err"]),
        "spearman_disagreement_copy_last_error": M.spearman(c["var"], c["base"]),
        "mean_error": float(np.mean(c["err"])),
    }


def main() -> None:
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a data directory with an eval split and models")
    p.add_argument("--version", help="model version (default: the champion)")
    args = p.parse_args()
    print(json.dumps(diagnose(args.data, args.version), indent=1))


if __name__ == "__main__":
    main()
