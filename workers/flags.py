"""The worker's command-line checks: argparse types that refuse a bad value, a parser that says so in one line,
and the flag each config field is set by (a config error names what the user typed).

``python -m workers.agent`` has them of its own: workers import only the wire contract of the
orchestrator (tests/test_layering.py), not ``orchestrator.cli.common``, whose checkers these word alike.
"""

from __future__ import annotations

import argparse
import math
import re
from typing import NoReturn

from orchestrator.protocol import one_line
from storage.records import TRAINABLE_SIZES, trainable_size

#: WorkerConfig fields that flags set (``naming_flag``).
FIELD_FLAGS = {"worker_id": "--id", "namespace": "--namespace", "mode": "--mode", "capabilities": "--capabilities",
               "tasks": "--capabilities", "shapes": "--capabilities", "image_size": "--size",
               "max_episodes": "--max-episodes", "realtime": "--realtime", "timeout_s": "--timeout",
               "part_bytes": "--upload-part-kb"}
#: Largest ``--realtime``: an episode of 1000 steps then lasts about 28 hours; more is a typo (and
#: ``inf`` would overflow the worker's wait after its first episode).
MAX_REALTIME = 1000.0


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line on stderr (no usage block) and exits 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)}\n")


def positive_int(text: str) -> int:
    """An integer >= 1 (``--max-episodes``)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, found {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, found {value}")
    return value


def realtime(text: str) -> float:
    """A ``--realtime`` slow-down: a number from 0 (flat out) to MAX_REALTIME; nan and inf are refused."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 <= value <= MAX_REALTIME:  # nan fails too
        raise argparse.ArgumentTypeError(f"expected a number from 0 (flat out) to {MAX_REALTIME:g}, found {text!r}")
    return value


def frame_size(text: str) -> int:
    """``--size``: a frame size a model trains on (the first upload fixes the catalog's)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a size in pixels, found {text!r}") from None
    if not trainable_size(value):
        raise argparse.ArgumentTypeError(f"expected {TRAINABLE_SIZES} (what a model trains on), found {value}")
    return value


def naming_flag(message: str) -> str:
    """A config error as the user typed it: ``"worker_id: expected ..."`` -> ``"--id: expected ..."``."""
    field = re.match(r"([a-z_]+)(\[\d+\])?: ", message)  # "shapes[2]: ..." is --capabilities' too
    if field is None or field.group(1) not in FIELD_FLAGS:
        return message
    return f"{FIELD_FLAGS[field.group(1)]}: {message[field.end():]}"
