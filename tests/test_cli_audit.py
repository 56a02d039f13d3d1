"""README.md's CLI table and every command's ``--help`` against the parsers, and bad values found by an audit
of both (each a one-line usage error, exit 2)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from orchestrator.cli import build_parser, main
from storage.catalog import Catalog
from tests.conftest import free_port, run_cli

README = Path(__file__).resolve().parents[1] / "README.md"
#: ``make bench ARGS="--only ..."``: ``python -m bench``'s flag, not a command's.
OTHER_PROGRAMS_FLAGS = {"--only"}


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """(command words, parser) of every command and sub-command, the top-level parser first."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, (*prefix, name))


def _flags(parser: argparse.ArgumentParser) -> set[str]:
    """The options of ``parser`` and of every sub-command under it."""
    return {flag for _, p in _commands(parser) for a in p._actions for flag in a.option_strings}


def _cli_table_synopses() -> dict[str, list[str]]:
    """Command -> the synopses README's CLI table gives it (the code spans of each row's first cell)."""
    section = README.read_text().split("## The CLI", 1)[1].split("\n## ", 1)[0]
    synopses: dict[str, list[str]] = {}
    for row in section.splitlines():
        if not row.startswith("| `"):
            continue
        first_cell = re.split(r"(?<!\\)\|", row)[1]
        for span in re.findall(r"`([^`]*)`", first_cell):
            span = span.replace("\\|", "|")
            synopses.setdefault(span.split()[0], []).append(span)
    return synopses


def test_the_readme_table_names_every_command_with_its_actions_and_only_their_flags() -> None:
    parser, synopses = build_parser(), _cli_table_synopses()
    top = {words[0]: p for words, p in _commands(parser) if len(words) == 1}
    assert set(synopses) == set(top)
    for name, spans in synopses.items():
        text = " ".join(spans)
        actions = [words[0] for words, _ in _commands(top[name]) if len(words) == 1]
        missing = [a for a in actions if not re.search(rf"(?<![\w-]){re.escape(a)}(?![\w-])", text)]
        assert not missing, f"README's row of {name} does not name {missing}"
        unknown = set(re.findall(r"--[a-z][a-z0-9-]*", text)) - _flags(top[name])
        assert not unknown, f"README gives {name} flags it does not take: {sorted(unknown)}"


def test_every_flag_the_readme_names_is_a_commands() -> None:
    named = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", README.read_text()))
    assert named - _flags(build_parser()) == OTHER_PROGRAMS_FLAGS


def test_every_commands_help_says_what_it_does() -> None:
    for words, p in _commands(build_parser()):
        assert p.description and p.description.strip(), f"activecollect {' '.join(words)} --help has no description"
    listed = build_parser().format_help()
    assert "create, pin, show" in listed  # eval-split's three actions


def test_operator_commands_say_what_they_need_and_their_exit_status() -> None:
    for words, p in _commands(build_parser()):
        if words and words[0] in ("queue", "workers", "stats", "watch") and not p._subparsers:
            assert "exit 1" in p.format_help() and "serve" in p.format_help(), words


@pytest.mark.parametrize("under", [False, True], ids=["file", "under-a-file"])
def test_secure_init_into_a_file_exits_2_in_one_line_and_writes_nothing(capsys, tmp_path, under) -> None:
    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    rc, out, err = run_cli(capsys, "secure", "init", str(afile / "sub" if under else afile))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"expected a directory for the profile, found a file at {afile}" in err
    assert sorted(tmp_path.iterdir()) == [afile] and afile.read_text() == "not a directory"


def test_queue_add_refuses_a_number_past_floats_range_as_a_usage_error(capsys) -> None:
    start = '{"shape": "T", "agent": [100, 100], "object": [256, 256, 1e400]}'  # json reads 1e400 as inf
    rc, out, err = run_cli(capsys, "queue", "add", "--shape", "T", "--start-state", start, "--timeout", "0.5",
                           "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "argument --start-state: expected a JSON object" in err and "1e400 is out of range for a number" in err


def test_bench_loop_refuses_an_out_that_is_a_file_as_a_usage_error(capsys, tmp_path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    rc, out, err = run_cli(capsys, "bench", "loop", "--out", str(afile))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"argument --out: expected an output directory, found a file at {afile}" in err


def test_bench_loop_refuses_the_out_of_a_run_stopped_midway_before_it_starts(capsys, tmp_path) -> None:
    """A run stopped (Ctrl-C) after its first arm made a catalog, and no summary.json: the same --out again
    is a usage error, said at once, not a traceback once torch has loaded."""
    out_dir = tmp_path / "loop"
    arm = out_dir / "seed0" / "active"
    Catalog(arm)  # what the stopped run left
    before = sorted(out_dir.rglob("*"))
    rc, out, err = run_cli(capsys, "bench", "loop", "--seeds", "1", "--out", str(out_dir))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"{out_dir} already holds a bench loop result, or a stopped run's; give a fresh --out" in err
    assert sorted(out_dir.rglob("*")) == before


def test_serve_in_client_mode_without_an_endpoint_to_connect_to_is_a_usage_error(capsys, tmp_path) -> None:
    """Zenoh refuses a client without a connect endpoint when the session opens: said before anything starts."""
    data = tmp_path / "data"
    data.mkdir()
    rc, out, err = run_cli(capsys, "serve", "--mode", "client", "--data", str(data), "--dashboard-port", "-1")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "error: --mode client needs --connect EP" in err
    assert list(data.iterdir()) == []


@pytest.mark.parametrize("argv", [["secure", "check"], ["stats", "--timeout", "0.5", "--zenoh-config"],
                                  ["router", "--zenoh-config"]], ids=" ".join)
@pytest.mark.parametrize("content", ["binary", "endless"])
def test_a_zenoh_config_that_is_not_text_exits_2_in_one_line(capsys, tmp_path, argv, content) -> None:
    """A binary file (or a device that never ends, as /dev/zero) given for a Zenoh config: one line naming it,
    not a UnicodeDecodeError's traceback (nor a read for ever)."""
    config = tmp_path / "zenoh.json5"
    if content == "binary":
        config.write_bytes(bytes(range(128, 256)) * 4)
    rc, out, err = run_cli(capsys, *argv, str(config if content == "binary" else Path("/dev/zero")))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert ("is not a Zenoh config: not UTF-8 text" if content == "binary" else "more than 1 MiB") in err


@pytest.mark.parametrize("argv", [["secure", "check"], ["stats", "--timeout", "30", "--zenoh-config"],
                                  ["router", "--zenoh-config"], ["serve", "--dashboard-port", "-1", "--zenoh-config"]],
                         ids=" ".join)
@pytest.mark.parametrize("section, endpoints, said", [
    ("connect", ["tcp/127.0.0.1:99999"], "connect/endpoints: port must be 0-65535, found '99999'"),
    ("connect", ["tcp/127.0.0.1"], "connect/endpoints: expected HOST:PORT after tcp/, found 'tcp/127.0.0.1'"),
    ("listen", {"router": ["tcp/127.0.0.1:0"], "peer": ["tcp/[::1:7447"]},
     "listen/endpoints/peer: expected HOST:PORT after tcp/, found 'tcp/[::1:7447'"),
], ids=["port-past-65535", "no-port", "per-mode-list"])
def test_a_zenoh_config_endpoint_of_a_bad_shape_exits_2_in_one_line(capsys, tmp_path, monkeypatch, argv, section,
                                                                    endpoints, said) -> None:
    """Checked as --connect and --listen are: unchecked, a port past 65535 was dialled (and "nothing listens
    there" said) and a connect endpoint without a port made a command wait its whole --timeout."""
    monkeypatch.setattr("orchestrator.cli.service.on_stop_signals", lambda *a, **k: lambda: None)
    config = tmp_path / "zenoh.json5"
    config.write_text(json.dumps({"mode": "peer", section: {"endpoints": endpoints},
                                  "scouting": {"multicast": {"enabled": False}}}))
    data = tmp_path / "data"
    extra = ["--data", str(data)] if argv[0] == "serve" else []
    rc, out, err = run_cli(capsys, *argv, str(config), *extra)
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert f"{config}: {said}" in err
    assert not data.exists()


@pytest.fixture(scope="module")
def champion(tmp_path_factory) -> tuple[Path, str]:
    """A data dir with 4 recorded train episodes of 5 frames, a pinned eval split and a trained champion;
    and one train episode's id."""
    data = tmp_path_factory.mktemp("champion") / "data"
    small = ("--size", "16", "--steps", "5", "--data", str(data))
    for argv in (("collect", "--episodes", "4", "--seed", "1", *small),
                 ("eval-split", "create", "--episodes", "2", "--seed", "99", *small),
                 ("train", "--members", "2", "--epochs", "1", "--device", "cpu", "--data", str(data))):
        assert main(list(argv)) == 0, argv
    return data, Catalog(data).list(split="train")[0].episode_id


def test_score_refuses_a_horizon_the_episode_has_no_room_for(capsys, champion) -> None:
    data, episode = champion
    rc, out, err = run_cli(capsys, "score", episode, "--horizon", "4", "--device", "cpu", "--data", str(data))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert (f"--horizon 4 is longer than episode {episode} allows: its 5 frames leave at most 3 after the model's "
            "2 context frames") in err
    rc, out, err = run_cli(capsys, "score", episode, "--horizon", "3", "--device", "cpu", "--data", str(data),
                           "--json")
    scored = json.loads(out)
    assert rc == 0 and scored["horizon"] == 3 and len(scored["top"]) == 1, err
