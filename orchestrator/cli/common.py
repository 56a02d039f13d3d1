"""Helpers every CLI command shares: the parser that exits 2 in one line, --data, --json output."""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NoReturn


from orchestrator import protocol
from orchestrator.dashboard import MAX_REQUEST_TIMEOUT_S, MIN_REQUEST_TIMEOUT_S, DashboardConfig
from orchestrator.protocol import MAX_EPISODE_STEPS, one_line
from orchestrator.retrainjob import cron_problem
from storage.catalog import Catalog
from storage.database import DB_NAME
from storage.records import TRAINABLE_SIZES, trainable_size
from uncertainty.config import MAX_EPOCHS, MAX_MEMBERS, MAX_WIDTH, TrainConfig

DEFAULT_DATA = Path("activecollect-data")


class UsageError(Exception):
    """A bad argument found after parsing (unknown episode, missing path): exit 2, one line."""


class _Commands(argparse._SubParsersAction):
    """Sub-commands whose ``--help`` opens with their one-line purpose (the ``help`` the command list shows)
    when they are given no ``description`` of their own."""

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        purpose = kwargs.get("help")
        if kwargs.get("description") is None and purpose:
            kwargs["description"] = purpose[0].upper() + purpose[1:] + ("" if purpose.endswith(".") else ".")
        return super().add_parser(name, **kwargs)


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error as one line on stderr and exits 2.

    Arguments a command does not know are its own error ("activecollect retrain: error:
    unrecognized arguments: ..."): argparse would hand them up to the top parser, whose
    message names no command. No command here passes unknown arguments on.
    """

    def add_subparsers(self, **kwargs: Any) -> argparse._SubParsersAction:
        kwargs.setdefault("action", _Commands)
        return super().add_subparsers(**kwargs)

    def error(self, message: str) -> NoReturn:
        flag = re.fullmatch(r"argument (--[\w-]+): expected one argument", message)
        if flag:  # e.g. --retrain-args '--from-champion': argparse took the value for an option
            message += f" (a value that starts with '-' needs '=': {flag[1]}=VALUE)"
        self.exit(2, f"{self.prog}: error: {one_line(message)}\n")

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace, extras


def directory_path(text: str, what: str = "a directory") -> Path:
    """A directory, or a path where one can be made (no file on the way); ``what`` names it in the error.

    Checks only; nothing is created. Raises ArgumentTypeError (exit 2) for a file in the way, and for an empty
    path (an unset shell variable), which Path would take for the current directory.
    """
    if not text:
        raise argparse.ArgumentTypeError(f"expected {what}, found an empty path (for this directory, give .)")
    path = Path(text)
    for step in (path, *path.parents):
        try:
            if not step.exists():
                continue
        except OSError as exc:  # e.g. a parent that cannot be searched
            raise argparse.ArgumentTypeError(f"cannot look at {step}: {exc.strerror}") from None
        if not step.is_dir():
            where = "" if step == path else f" on the way to {path}"
            raise argparse.ArgumentTypeError(f"expected {what}, found a file at {step}{where}")
        break
    return path


def data_dir(text: str) -> Path:
    """A ``--data`` path (``directory_path``)."""
    return directory_path(text, "a data directory")


def add_data_arg(p: argparse.ArgumentParser) -> None:
    # a str default, so argparse runs data_dir on it too
    p.add_argument("--data", type=data_dir, default=str(DEFAULT_DATA), metavar="DIR",
                   help=f"data directory (catalog, episodes, models, reports); default ./{DEFAULT_DATA}")


def add_json_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print machine-readable JSON instead of text")


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2, sort_keys=True, default=str)
    sys.stdout.write("\n")


def _int_at_least(text: str, low: int, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, found {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected {what}, found {value}")
    return value


def int_in(text: str, low: int, high: int, what: str, most: str) -> int:
    """An integer from ``low`` (below: "expected WHAT") to ``high`` (above: "expected at most HIGH MOST"), for a
    flag whose larger values would only fail, hang or crash later."""
    value = _int_at_least(text, low, what)
    if value > high:
        raise argparse.ArgumentTypeError(f"expected at most {high} {most}, found {value}")
    return value


def positive_int(text: str) -> int:
    return _int_at_least(text, 1, "a positive integer")


#: The most episodes one ``collect`` or ``eval-split create`` records: each is planned and checked against the
#: catalog before the first is recorded (~0.5 ms each, so ~1 min at the cap); run more commands, each with its
#: own --seed, for more.
MAX_COLLECT_EPISODES = 100_000


def episode_count(text: str) -> int:
    """``--episodes`` of the commands that record episodes: 1..``MAX_COLLECT_EPISODES``."""
    return int_in(text, 1, MAX_COLLECT_EPISODES, "a positive integer",
                  "episodes per command (each is planned before the first is recorded)")


def given_path(text: str) -> Path:
    """A path given as an argument to read from: an empty one (an unset shell variable) is refused, where Path
    would take it for the current directory."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, found an empty path (for this directory, give .)")
    return Path(text)


def ensemble_size(text: str) -> int:
    """``--members`` of the commands that train or score: one member cannot disagree (no score, no calibration)."""
    return int_in(text, 2, MAX_MEMBERS, "an ensemble of at least 2 members (one cannot disagree)", "members")


def epoch_count(text: str) -> int:
    """``--epochs`` of the commands that train: 1..``MAX_EPOCHS`` (``10**20`` trained until Ctrl-C)."""
    return int_in(text, 1, MAX_EPOCHS, "a positive integer", "epochs")


def non_negative_int(text: str) -> int:
    return _int_at_least(text, 0, "an integer >= 0")


#: Most torch threads a flag takes: torch's pool of many thousands fails (libgomp "Thread creation failed") or
#: crashes the process (SIGSEGV at 100000) at its first matrix product, long after the flag was taken.
MAX_TORCH_THREADS = 1024


def torch_threads(text: str) -> int:
    """A number of torch threads, 0 (torch's default, one per core) to ``MAX_TORCH_THREADS``."""
    return int_in(text, 0, MAX_TORCH_THREADS, "an integer >= 0", "threads")


def _int(text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, found {text!r}") from None


#: The fewest steps an episode may have (``protocol.MIN_EPISODE_STEPS``): a catalog or eval split of
#: shorter episodes fails every retrain.
MIN_EPISODE_STEPS = protocol.MIN_EPISODE_STEPS


def trainable_image_size(text: str) -> int:
    """A frame size to record or train at (``storage.records.trainable_size``)."""
    value = _int(text, "a size in pixels")
    if not trainable_size(value):
        raise argparse.ArgumentTypeError(f"expected {TRAINABLE_SIZES} (what a model trains on), "
                                         f"found {value}")
    return value


def episode_steps(text: str) -> int:
    """Steps of an episode to record: enough to learn from (``MIN_EPISODE_STEPS``), at most the
    protocol's ``MAX_EPISODE_STEPS``."""
    value = _int(text, "a whole number of steps")
    if value < MIN_EPISODE_STEPS:
        raise argparse.ArgumentTypeError(
            f"expected at least {MIN_EPISODE_STEPS} steps (a model learns from {TrainConfig.context} frames of "
            f"context and the next one), found {value}")
    if value > MAX_EPISODE_STEPS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_EPISODE_STEPS} steps, found {value}")
    return value


def dashboard_port(text: str) -> int:
    """A dashboard port: -1 (no dashboard), 0 (any free port) or a TCP port."""
    value = _int(text, "-1 (none), 0 (any) or a TCP port")
    if not -1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected -1 (none), 0 (any free port) or a TCP port in 1..65535, "
                                         f"found {value}")
    return value


def fraction(text: str) -> float:
    """A number in [0, 1) (a relative improvement)."""
    value = finite_float(text)
    if not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1) such as 0.02, found {text!r}")
    return value


def unit(text: str) -> float:
    """A number in [0, 1] (a share that may be none)."""
    value = finite_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1] such as 0.25, found {text!r}")
    return value


def share(text: str) -> float:
    """A share in (0, 1] (of a round, of a budget)."""
    value = finite_float(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"expected a share in (0, 1] such as 0.5, found {text!r}")
    return value


def cron_expression(text: str) -> str:
    """A retrain schedule: a cron expression of 5 fields such as ``0 * * * *``, or an @-name, that fires
    ('' = none; see ``orchestrator.retrainjob.cron_problem``)."""
    problem = cron_problem(text) if text else None
    if problem:
        raise argparse.ArgumentTypeError(f"expected {problem.removeprefix('cron must be ')}"
                                         if problem.startswith("cron must be ") else problem)
    return text


#: Config fields that CLI flags set under another name. A config's ValueError names its field
#: (``dashboard_port must be ...``); shown to a user it names the flag (see ``config_error``).
#: Only names with an underscore, which never stand for a plain word of a message.
FLAGS = {"round_episodes": "--round", "min_rel_improvement": "--min-improvement",
         "dashboard_port": "--dashboard-port", "dashboard_max_connections": "--dashboard-max-connections",
         "dashboard_request_timeout_s": "--dashboard-request-timeout", "retrain_every": "--retrain-every",
         "every_episodes": "--retrain-every", "retrain_cron": "--retrain-cron", "retrain_args": "--retrain-args",
         "image_size": "--image-size", "eval_episodes": "--eval-episodes", "eval_seed": "--eval-seed",
         "batch_size": "--batch-size", "max_windows": "--max-windows", "from_champion": "--from-champion",
         "variance_head": "--variance-head", "lease_s": "--lease-s", "reap_interval_s": "--reap-interval-s",
         "seed_requests": "--seed-requests", "min_queued": "--min-queued", "max_connections": "--max-connections",
         "request_timeout_s": "--request-timeout", "active_policy": "--active-policy",
         "random_physics": "--random-physics", "progress_horizon": "--progress-horizon"}


#: ``TrainConfig`` fields that ``train`` and ``retrain`` set under a flag of the same name.
TRAIN_FLAGS = {name: f"--{name}" for name in ("members", "epochs", "lr", "widths", "seed", "device")}


def config_error(exc: Exception, flags: Mapping[str, str] | None = None) -> UsageError:
    """A configuration's ValueError as a usage error that names flags instead of fields.

    ``flags``: this command's own names (plain words such as ``budget``, or a field its flag
    names otherwise, e.g. ``image_size`` -> ``--size``), over ``FLAGS``.
    """
    names = {**FLAGS, **(flags or {})}
    # Whole words only, and not inside a path, a file name or a quoted value (/data/image_size, 'mode').
    word = r"(?<![\w/.'\"-])[a-z][a-z0-9_]*(?![\w/.'\"-])"
    return UsageError(re.sub(word, lambda m: names.get(m.group(0), m.group(0)), str(exc)))


def tcp_port(text: str) -> int:
    """A TCP port to listen on, 0 for any free one."""
    value = _int_at_least(text, 0, "a TCP port in 0..65535")
    if value > 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port in 0..65535, found {value}")
    return value


def finite_float(text: str) -> float:
    """A number other than nan / inf (argparse's float takes both)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, found {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (a time, a rate): nan and inf are refused too."""
    try:
        value = finite_float(text)
    except argparse.ArgumentTypeError:
        value = math.nan
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, found {text!r}")
    return value


#: What every ``--device`` takes: the devices ``TrainConfig.device`` names (it takes no ``cuda:N``).
DEVICES = ("auto", "cpu", "cuda")


def seconds_in(low: float, high: float) -> Callable[[str], float]:
    """An argparse type: a finite number of seconds in [``low``, ``high``] (nan and inf refused)."""
    def seconds(text: str) -> float:
        try:
            value = finite_float(text)
        except argparse.ArgumentTypeError:
            value = math.nan
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected seconds in {low:g}..{high:g}, found {text!r}")
        return value
    return seconds


def torch_device(text: str) -> str:
    """A ``--device``: auto (CUDA when there is one, else the CPU), cpu, or cuda where torch sees CUDA.

    Checked when the arguments are parsed, so a command refuses in one line (exit 2) before it loads
    a model or starts training. torch is imported only to check ``cuda``: argparse runs this on the
    default too, and most commands never need torch.
    """
    if text not in DEVICES:
        hint = " (pick a GPU with CUDA_VISIBLE_DEVICES=N and --device cuda)" if text.startswith("cuda:") else ""
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(DEVICES)}{hint}, found {text!r}")
    if text == "cuda":
        import torch  # (only here: the start-up cost of every command that does not ask for cuda)

        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"cuda: CUDA is not available on this machine (torch "
                                             f"{torch.__version__}); use --device cpu or leave it out")
    return text


def _request_timeout(text: str) -> float:
    value = positive_float(text)
    if value > MAX_REQUEST_TIMEOUT_S:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_REQUEST_TIMEOUT_S:g} seconds (a day), found {text!r}")
    if value < MIN_REQUEST_TIMEOUT_S:  # (1e-300 dropped every client before its request came)
        raise argparse.ArgumentTypeError(f"expected at least {MIN_REQUEST_TIMEOUT_S:g} seconds (shorter drops "
                                         f"clients before their request arrives), found {text!r}")
    return value


#: The most dashboard connections served at once (a thread each): past the system's thread limit, each one more
#: would be an ERROR with a traceback, not a 503.
MAX_DASHBOARD_CONNECTIONS = 4096


def _max_connections(text: str) -> int:
    return int_in(text, 1, MAX_DASHBOARD_CONNECTIONS, "a positive integer", "connections (a thread each)")


def add_dashboard_limit_args(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """``--[PREFIX]max-connections`` and ``--[PREFIX]request-timeout`` (``args.max_connections``,
    ``args.request_timeout``): the dashboard's limits on clients, for ``dashboard`` and ``serve``."""
    d = DashboardConfig
    p.add_argument(f"--{prefix}max-connections", type=_max_connections, default=d.max_connections, metavar="N",
                   dest="max_connections",
                   help=f"dashboard connections served at once, at most {MAX_DASHBOARD_CONNECTIONS}; one more is "
                        f"answered 503 with Retry-After (default {d.max_connections})")
    p.add_argument(f"--{prefix}request-timeout", type=_request_timeout, default=d.request_timeout_s, metavar="S",
                   dest="request_timeout",
                   help=f"seconds a dashboard client may take to send its whole request before it is dropped, "
                        f"{MIN_REQUEST_TIMEOUT_S:g} to {MAX_REQUEST_TIMEOUT_S:g} (default {d.request_timeout_s:g})")


def require_frame_size(data: Path, size: int, flag: str) -> None:
    """UsageError (exit 2) when ``data`` holds a catalog of another frame size than ``size`` (given as
    ``flag``): one other episode would fail every retrain there. Nothing is created."""
    if not (Path(data) / DB_NAME).is_file():
        return
    held = Catalog(data, make_episodes_dir=False).frame_size()
    if held is not None and held != size:
        if not trainable_size(held):  # made before sizes were checked: no flag value matches it
            raise UsageError(f"{data} holds {held}px episodes, a size no model trains on: give another --data")
        raise UsageError(f"{data} holds {held}px episodes and its models predict {held}px frames: "
                         f"give {flag} {held}, or another --data")


def require_catalog(data: Path) -> None:
    """UsageError (exit 2) unless ``data`` holds a catalog; nothing is created."""
    if not (data / DB_NAME).is_file():
        raise UsageError(f"no catalog at {data} (give --data DIR, or collect episodes first)")


def existing_catalog(args: argparse.Namespace, writes: bool = False) -> Catalog:
    """The catalog at ``args.data``; UsageError (exit 2) unless there is one. A command that only reads it
    creates nothing; one that ``writes`` (moves episode files) makes its episodes/ folder where none is."""
    data = Path(args.data)
    require_catalog(data)
    return Catalog(data, make_episodes_dir=writes)


def add_episode_args(p: argparse.ArgumentParser, steps: int, image_size: int) -> None:
    """``--steps`` and ``--image-size`` of the commands that collect and train (``run``, ``bench loop``)."""
    p.add_argument("--steps", type=episode_steps, default=steps, metavar="T",
                   help=f"steps per episode, of the training episodes and of the eval split's "
                        f"({MIN_EPISODE_STEPS}..{MAX_EPISODE_STEPS}; default {steps})")
    p.add_argument("--image-size", type=trainable_image_size, default=image_size, metavar="PX",
                   help=f"frame size in pixels, {TRAINABLE_SIZES} (default {image_size})")


def channel_widths(text: str) -> tuple[int, int, int]:
    """``--widths``: a fresh model's three channel widths, ``A,B,C``."""
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three integers like 8,16,32, found {text!r}") from None
    if len(widths) != 3 or min(widths) < 1:
        raise argparse.ArgumentTypeError(f"expected three positive integers like 8,16,32, found {text!r}")
    if max(widths) > MAX_WIDTH:
        raise argparse.ArgumentTypeError(f"expected channel widths of at most {MAX_WIDTH}, found {text!r}")
    return widths  # type: ignore[return-value]
