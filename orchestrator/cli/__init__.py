"""The ``activecollect`` command: argument parsing and printing only.

Each command group lives in its own module with ``register(subparsers)`` and/or,
for benchmarks, ``register_bench(bench_subparsers)``; every sub-parser sets
``func(args) -> int``.
"""

from __future__ import annotations

import importlib.metadata
import os
import signal
import sys

from orchestrator import transport
from orchestrator.protocol import one_line
from orchestrator.signals import ctrl_c_put_off
from orchestrator.cli import collect, common, loop, loopbench, models, operator, registry, secure, service
from storage.database import space_note
from storage.errors import StorageError

# (collect adds cli/episodes.py's commands after its own)
_MODULES = (collect, models, registry, service, operator, loop, loopbench, secure)


def build_parser() -> common.Parser:
    parser = common.Parser(
        prog="activecollect",
        description="Active data collection for robot world models: an ensemble's disagreement "
                    "decides where simulated pushing collectors gather the next episodes.",
    )
    parser.add_argument("--version", action="version", version=f"activecollect {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=common.Parser)
    sub.required = True
    bench = sub.add_parser("bench", help="benchmarks (sim, score, dispatch, loop, loop-summary); --json for figures")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", parser_class=common.Parser)
    bench_sub.required = True
    for module in _MODULES:
        if hasattr(module, "register"):
            module.register(sub)
        if hasattr(module, "register_bench"):
            module.register_bench(bench_sub)
    return parser


def _version() -> str:
    """The installed distribution's version (pyproject.toml's); "unknown" when the package runs uninstalled (from
    a source tree on ``PYTHONPATH``)."""
    try:
        return importlib.metadata.version("activecollect")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (not installed: run from a source tree)"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with ctrl_c_put_off():  # (a KeyboardInterrupt raised inside pymunk's callbacks is lost, or a segfault)
            return int(args.func(args) or 0)
    except (common.UsageError, transport.SecureConfigError) as exc:
        print(f"activecollect: error: {one_line(str(exc))}", file=sys.stderr)  # a path may hold a newline
        return 2
    except KeyboardInterrupt:
        print("activecollect: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`... | head`): stop quietly, as `yes | head` does
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 128 + signal.SIGPIPE
    except (MemoryError, RuntimeError) as exc:
        # numpy's MemoryError; torch's CPU allocator ("can't allocate memory") and torch.OutOfMemoryError (CUDA)
        # are RuntimeErrors: one line, exit 1, as for a full disk. Other RuntimeErrors are bugs: keep the traceback.
        text = str(exc)
        if not (isinstance(exc, MemoryError) or "can't allocate memory" in text
                or type(exc).__name__ == "OutOfMemoryError"):
            raise
        print(f"activecollect: out of memory: {one_line(text.splitlines()[0] if text else 'an allocation failed')} "
              "(a smaller --batch, --batch-size, --size, --members or --widths needs less)", file=sys.stderr)
        return 1
    except (StorageError, OSError) as exc:  # a full disk, a damaged catalog: one line, not a traceback
        detail = str(exc) if isinstance(exc, StorageError) else f"{exc}{space_note(exc.filename or '.')}"
        print(f"activecollect: {one_line(detail)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
