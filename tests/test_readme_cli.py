"""README.md's command lines against the real parsers: its examples parse, each code span that names a command
gives it only its own flags (the CLI table's rows action by action), and what README and ``--help`` say of
``queue ls``'s order is what the queue does. (tests/test_cli_audit.py checks the table's flags per command.)"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from orchestrator import admin
from orchestrator.cli import build_parser
from storage.queue import RequestQueue
from storage.requests import NewRequest
from tests.test_cli_audit import _cli_table_synopses

README = Path(__file__).resolve().parents[1] / "README.md"
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def _actions(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The sub-commands of ``parser`` by name ({} when it has none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {flag for action in parser._actions for flag in action.option_strings}


def _example_lines() -> list[str]:
    """README's example command lines: each ``activecollect ...`` line of its code blocks (a trailing ``\\``
    continues it, ``#`` starts a comment) and each ``make run ARGS="..."``, as ``activecollect`` arguments."""
    text = README.read_text()
    lines = []
    for block in re.findall(r"^```[a-z]*\n(.*?)^```", text, re.S | re.M):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" #", 1)[0].strip()
            if line.startswith("activecollect "):
                lines.append(line.removeprefix("activecollect "))
    lines += ["run " + args for args in re.findall(r'`make run ARGS="([^"`]*)"`', text)]
    return lines


def test_the_readme_has_examples_to_check() -> None:
    lines = _example_lines()
    assert any(line.startswith("secure init") for line in lines) and any(line.startswith("run ") for line in lines)
    assert len(lines) >= 10, lines


@pytest.mark.parametrize("line", _example_lines())
def test_every_readme_example_parses(line: str) -> None:
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        try:
            build_parser().parse_args(shlex.split(line))
        except SystemExit:
            pytest.fail(f"README's `activecollect {line}` is refused: {stderr.getvalue().strip()}")


def _command_spans() -> list[tuple[str, list[str]]]:
    """Each inline code span of README that starts with a command's words (``serve --lease-s``, ``bench loop
    --out``, ``make run ARGS="..."``): (the span, its words after ``activecollect``)."""
    spans = []
    commands = _actions(build_parser())
    synopses = {s for spans_of in _cli_table_synopses().values() for s in spans_of}  # checked below
    for span in re.findall(r"(?<!`)`([^`\n]+)`(?!`)", README.read_text()):
        if span.replace("\\|", "|") in synopses:
            continue
        words = span.removeprefix("make run ARGS=\"").removeprefix("activecollect ").replace("\\|", "|")
        words = ("run " + words.rstrip('"')) if span.startswith("make run ARGS=") else words
        try:
            argv = shlex.split(words)
        except ValueError:
            argv = words.split()
        if argv and argv[0] in commands:
            spans.append((span, argv))
    return spans


def test_every_command_span_gives_its_command_only_its_own_flags() -> None:
    """``--retrain-args 'ARGS'``'s ARGS are `retrain`'s flags."""
    top, retrain = build_parser(), _actions(build_parser())["retrain"]
    unknown = []
    for span, argv in _command_spans():
        parser, i = top, 0
        while i < len(argv) and argv[i] in _actions(parser):
            parser, i = _actions(parser)[argv[i]], i + 1
        for before, word in zip(argv[i - 1:], argv[i:]):
            if before == "--retrain-args":
                unknown += [f"{flag} in `{span}`" for flag in FLAG.findall(word) if flag not in _options(retrain)]
            elif word.startswith("--") and word.split("=")[0] not in _options(parser):
                unknown.append(f"{word.split('=')[0]} in `{span}`")
    assert len(_command_spans()) >= 10
    assert not unknown, f"README names flags its commands do not take: {unknown}"


def _top_level_split(synopsis: str) -> list[str]:
    """``a [x|y] b|c d`` -> ``["a [x|y] b", "c d"]``: the ``|`` outside brackets."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(synopsis):
        depth += {"[": 1, "]": -1}.get(ch, 0)
        if ch == "|" and depth == 0:
            parts.append(synopsis[start:i])
            start = i + 1
    return [*parts, synopsis[start:]]


def test_the_readme_tables_synopses_give_each_action_only_its_own_flags() -> None:
    """`episodes ls [...]|verify [--quarantine]|...`: each flag where its action takes it, not just somewhere
    under the command (what tests/test_cli_audit.py checks)."""
    commands, checked, misplaced = _actions(build_parser()), 0, []
    for name, spans in _cli_table_synopses().items():
        actions = _actions(commands[name])
        for span in spans:
            if not actions:
                continue
            for segment in _top_level_split(span.removeprefix(name).strip()):
                action = segment.split()[0]
                assert action in actions, f"README's `{span}`: {action!r} is no action of {name}"
                checked += 1
                misplaced += [f"{name} {action} {flag}" for flag in FLAG.findall(segment)
                              if flag not in _options(actions[action])]
    assert checked >= 20 and not misplaced, misplaced


def test_queue_ls_lists_in_lease_order_only_with_status_queued_as_readme_and_help_say(tmp_path: Path) -> None:
    """Without --status the list is newest change first, queued requests too; lease order (priority, then
    arrival) is --status queued's. README and the help used to say queued requests were in lease order."""
    queue = RequestQueue(tmp_path / "catalog.sqlite")
    try:
        first, _ = queue.enqueue(NewRequest("push", "T", {}), now=1000.0)
        second, _ = queue.enqueue(NewRequest("push", "box", {}), now=2000.0)

        def listed(args: dict) -> list[str]:
            return [r["id"] for r in admin.handle("queue.ls", args, queue=queue)["requests"]]

        assert listed({}) == [second.id, first.id]
        assert listed({"status": "queued"}) == [first.id, second.id]
    finally:
        queue.close()
    queue_ls = _actions(_actions(build_parser())["queue"])["ls"]
    assert "newest change first (--status queued: in lease order)" in queue_ls.format_help()
    assert "`queue ls`: newest change first (`--status queued`: in lease order)" in README.read_text()
