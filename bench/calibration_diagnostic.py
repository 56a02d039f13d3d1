"""Where does the champion's error come from, and does disagreement see it? (BENCHMARKS.md, calibration)

For every horizon-1 window of the pinned eval split of a data directory, with the champion (or a
given version): the members' variance (disagreement), the ensemble mean's error, and the
copy-last error (how much the frame changes), each also split into changing and static pixels
(a pixel changes when the true or the predicted next frame differs from the last by > 2 %).
Prints the Spearman correlations between them. Inference only.

    .venv/bin/python bench/calibration_diagnostic.py --data DIR [--version V]

--version takes what ``activecollect models show`` takes (a version or a unique prefix of one); a
--data that is no data directory, a version it does not hold (or a prefix of several) and a directory with
no champion and no --version exit 2 in one line before anything is loaded.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from orchestrator.cli.common import Parser, UsageError
from orchestrator.cli.registry import resolve_model
from storage.catalog import Catalog
from storage.database import DB_NAME
from storage.models import ModelRegistry
from uncertainty import metrics as M
from uncertainty.checkpoint import load_ensemble
from uncertainty.train import build_windows, load_eval

#: A pixel "changes" when some channel moves by more than this (frames in [0, 1]).
CHANGE = 0.02


def diagnose(data: Path, version: str, batch: int = 64) -> dict:
    """The figures of ``version`` (registered in ``data``, as ``resolve_version`` names it) on ``data``'s eval split."""
    catalog, registry = Catalog(data), ModelRegistry(data)
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


def resolve_version(data: Path, version: str | None) -> str:
    """The registered version ``version`` names as ``models show`` takes it (in full or by a unique prefix), or
    the champion when it is None. Raises ``UsageError`` when ``data`` is no data directory or holds no such model."""
    if not (data / DB_NAME).is_file():
        raise UsageError(f"--data {data}: not a data directory (no {DB_NAME})")
    registry = ModelRegistry(data)
    if version is None:
        champion = registry.champion()
        if champion is None:
            raise UsageError(f"--data {data}: no champion; give --version")
        return champion
    return resolve_model(registry, version).version


def build_parser() -> Parser:
    p = Parser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a data directory with an eval split and models")
    p.add_argument("--version", help="model version, or a unique prefix of one as `activecollect models show` "
                                     "takes (default: the champion)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    try:
        version = resolve_version(args.data, args.version)
    except UsageError as exc:
        p.error(str(exc))
    print(json.dumps(diagnose(args.data, version), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
