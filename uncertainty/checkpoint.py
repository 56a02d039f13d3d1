"""Ensemble checkpoints: bytes in the model registry, loaded back with ``weights_only`` safety.

The weights file is a ``torch.save`` of plain containers and tensors (no
pickled classes), so ``torch.load(weights_only=True)`` reads it; the predictor
config, member count and action normalisation travel inside it, so a checkpoint
is self-describing. The registry checks the bytes' sha256; this module checks
that they describe an ensemble.
"""

from __future__ import annotations

import io
from typing import Any

import torch

from storage.errors import RegistryError
from storage.models import ModelRegistry
from storage.rows import Snapshot
from uncertainty.ensemble import Ensemble, default_device
from uncertainty.errors import CheckpointError, ConfigError
from uncertainty.model import Predictor, PredictorConfig

FORMAT = "activecollect-ensemble"
FORMAT_VERSION = 1


def ensemble_to_bytes(ensemble: Ensemble) -> bytes:
    """Serialise weights, predictor config, member count, seed and action normalisation."""
    payload = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "predictor": ensemble.config.to_dict(), "members": ensemble.members, "seed": ensemble.seed,
        "params": {name: p.detach().cpu().contiguous() for name, p in zip(ensemble.names, ensemble.params)},
        "action_mean": ensemble.action_mean.detach().cpu(), "action_std": ensemble.action_std.detach().cpu(),
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def ensemble_from_bytes(data: bytes, device: torch.device | str | None = None) -> Ensemble:
    """Rebuild an ensemble from ``ensemble_to_bytes``; raises ``CheckpointError`` naming what is wrong."""
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 -- torch's unpickler meets damaged bytes with any error (IndexError, ...)
        raise CheckpointError(f"checkpoint is not a readable torch file ({len(data)} bytes): "
                              f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(f"checkpoint format must be {FORMAT!r}, found {found!r}")
    if payload.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint format_version must be {FORMAT_VERSION}, "
                              f"found {payload.get('format_version')!r}")
    try:
        config = PredictorConfig.from_dict(payload["predictor"])
        members, seed = int(payload["members"]), int(payload["seed"])
    except (KeyError, TypeError, ValueError, OverflowError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint config is invalid: {type(exc).__name__}: {exc}") from exc
    _check_shapes(config, members, payload.get("params"))
    try:
        ensemble = Ensemble(config, members=members, seed=seed)
    except (ValueError, OverflowError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint config is invalid: {type(exc).__name__}: {exc}") from exc
    _load_tensors(ensemble, payload)
    return ensemble.to(device if device is not None else default_device())


def _check_shapes(config: PredictorConfig, members: int, params: Any) -> None:
    """Refuses a config whose members' parameters are not the tensors the file holds, before building it.

    The config and member count are only claims: built as they stand, widths of 200,000 channels or
    10 million members would allocate terabytes or loop for hours before the tensors were compared.
    The shapes are taken from a predictor on the ``meta`` device (no memory), so what gets allocated
    afterwards is the tensors actually read from the file plus one predictor's buffers (``Ensemble``
    builds one predictor for all its members; ``image_size`` is capped by ``PredictorConfig``).
    """
    if members < 1:
        raise CheckpointError(f"checkpoint config is invalid: members must be >= 1, found {members}")
    if (not isinstance(params, dict) or not all(isinstance(t, torch.Tensor) for t in params.values())
            or not all(isinstance(k, str) for k in params)):
        found = type(params).__name__ if not isinstance(params, dict) else "other keys or values"
        raise CheckpointError(f"checkpoint parameters must be a dict of names to tensors, found {found}")
    odd = next((k for k, t in params.items() if not _dense_float(t)), None)
    if odd is not None:
        t = params[odd]
        raise CheckpointError(f"checkpoint parameter {odd} must be a dense floating-point tensor, found a "
                              f"{t.layout} {t.dtype} tensor on {t.device}")
    try:
        with torch.device("meta"):
            template = Predictor(config)
    except (TypeError, ValueError, OverflowError, RuntimeError) as exc:  # sizes past torch's 64 bits
        raise CheckpointError(f"checkpoint config is invalid: {config} makes no predictor: {type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''}") from exc
    expected = {name: (members, *p.shape) for name, p in template.named_parameters()}
    if set(params) != set(expected):
        raise CheckpointError(f"checkpoint parameters must be {sorted(expected)}, found {sorted(params)}")
    for name, shape in expected.items():
        if tuple(params[name].shape) != shape:
            raise CheckpointError(f"checkpoint config does not match its weights: parameter {name} of "
                                  f"{members} member(s) of {config} must have shape {shape}, "
                                  f"found {tuple(params[name].shape)}")


def _dense_float(t: torch.Tensor) -> bool:
    """Whether ``t`` holds numbers a parameter can take: dense floats in memory (not sparse, not ``meta``, not
    integers or complex numbers that ``copy_`` would cast without a word)."""
    return t.layout == torch.strided and t.is_floating_point() and t.device.type == "cpu"


def _load_tensors(ensemble: Ensemble, payload: dict[str, Any]) -> None:
    params = payload["params"]  # names and shapes checked by _check_shapes
    with torch.no_grad():
        for name, p in zip(ensemble.names, ensemble.params):
            t = params[name]
            if not bool(torch.isfinite(t).all()):
                raise CheckpointError(f"checkpoint parameter {name} has non-finite values")
            p.copy_(t)
        for key in ("action_mean", "action_std"):
            t = payload.get(key)
            if (not isinstance(t, torch.Tensor) or not _dense_float(t) or t.shape != (ensemble.config.action_dim,)
                    or not bool(torch.isfinite(t).all())):
                found = (f"a {t.layout} {t.dtype} tensor of shape {tuple(t.shape)}" if isinstance(t, torch.Tensor)
                         else repr(t)[:80])  # (a tensor's repr runs over lines)
                raise CheckpointError(f"checkpoint {key} must be a finite floating-point tensor of shape "
                                      f"({ensemble.config.action_dim},), found {found}")
        try:
            ensemble.set_action_stats(payload["action_mean"].numpy(), payload["action_std"].numpy())
        except ConfigError as exc:
            raise CheckpointError(f"checkpoint action normalisation is invalid: {exc}") from exc


def save_candidate(registry: ModelRegistry, ensemble: Ensemble, metrics: dict[str, Any], snapshot_id: str,
                   eval_hash: str, parent: str | None = None,
                   train_config: dict[str, Any] | None = None, snapshot: Snapshot | None = None) -> str:
    """Register the ensemble as a candidate and return its version (the gate is the caller's call);
    ``snapshot``: the episodes it was trained on (``ModelRegistry.snapshot`` reads them back).

    Raises ``storage.errors.RegistryError`` when the registry refuses it.
    """
    config = {"predictor": ensemble.config.to_dict(), "members": ensemble.members, "seed": ensemble.seed,
              "format": FORMAT, "format_version": FORMAT_VERSION, "train": train_config or {}}
    return registry.register(ensemble_to_bytes(ensemble), config, metrics, snapshot_id, eval_hash, parent,
                             snapshot=snapshot)


def load_ensemble(registry: ModelRegistry, version: str | None = None,
                  device: torch.device | str | None = None) -> Ensemble:
    """Load ``version`` (default: the champion) in eval mode.

    Raises ``storage.errors.RegistryError`` for an unknown version or when there is
    no champion, ``CorruptCheckpointError`` when the weights fail their sha256, and
    ``CheckpointError`` (also a ``CorruptCheckpointError``) when they are not an ensemble.
    """
    if version is None:
        version = registry.champion()
        if version is None:
            raise RegistryError("no champion model yet: train one first (activecollect train)")
    ensemble = ensemble_from_bytes(registry.load_weights(version), device)
    ensemble.version = version
    return ensemble.eval()
