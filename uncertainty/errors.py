"""The uncertainty package's exceptions: one root, one subclass per way a model or its data can be wrong."""

from storage.errors import CorruptCheckpointError


class UncertaintyError(Exception):
    """Root of every error raised by ``uncertainty``."""


class ConfigError(UncertaintyError, ValueError):
    """A model, training or benchmark configuration is out of range."""


class DataError(UncertaintyError):
    """Episodes cannot be turned into training or evaluation windows (too short, wrong size, empty split)."""


class DivergedError(UncertaintyError):
    """Training produced a non-finite loss: the weights are no model, so nothing is evaluated or registered."""


class CheckpointError(UncertaintyError, CorruptCheckpointError):
    """A checkpoint's bytes (sha256 intact) do not describe an ensemble this code can load.

    Also a ``storage.errors.CorruptCheckpointError``, so callers that refuse corrupt
    checkpoints catch both kinds with one clause.
    """
