"""Bad arguments end in one line on stderr and exit 2, whatever the command; failures at run time exit 1."""

from __future__ import annotations

import argparse

import pytest

from orchestrator import endpoints
from orchestrator.cli import build_parser, common
from storage.catalog import Catalog
from tests.conftest import free_port, run_cli


def _subparsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """(command words, parser) of every leaf command."""
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not actions:
        yield prefix, parser
    for action in actions:
        for name, sub in action.choices.items():
            yield from _subparsers(sub, (*prefix, name))


def _data_commands() -> list[tuple[str, ...]]:
    return [words for words, p in _subparsers(build_parser())
            if any(a.dest == "data" for a in p._actions)]


def test_every_data_argument_is_checked_the_same_way() -> None:
    commands = _data_commands()
    assert {("collect",), ("ingest",), ("eval-split", "create"), ("bench", "dispatch")} <= set(commands)
    for words, p in _subparsers(build_parser()):
        for action in p._actions:
            if action.dest == "data":
                assert action.type is common.data_dir, words


#: Arguments each command needs besides --data to get as far as using it.
_NEEDS = {("ingest",): ["somefile.mcap"], ("score",): ["e1"], ("models", "show"): ["m1"],
          ("models", "promote"): ["m1"], ("episodes", "show"): ["e1"]}


@pytest.mark.parametrize("words", _data_commands(), ids=" ".join)
@pytest.mark.parametrize("under", [False, True], ids=["file", "under-a-file"])
def test_data_that_is_a_file_exits_2_in_one_line(capsys, tmp_path, words, under) -> None:
    afile = tmp_path / "afile"
    afile.write_text("not a directory")
    data = afile / "sub" if under else afile
    rc, out, err = run_cli(capsys, *words, *_NEEDS.get(words, []), "--data", str(data))
    assert rc == 2 and err.count("\n") == 1, err
    assert f"expected a data directory, found a file at {afile}" in err
    assert afile.read_text() == "not a directory"


def _connect() -> list[str]:
    return ["--connect", f"tcp/127.0.0.1:{free_port()}"]


@pytest.mark.parametrize("argv, words", [
    (["queue", "ls", "--timeout", "nan"], "expected seconds"),
    (["queue", "ls", "--timeout", "inf"], "expected seconds"),
    (["queue", "ls", "--timeout", "-1"], "expected seconds"),
    (["queue", "ls", "--timeout", "1e300"], "expected seconds"),
    (["stats", "--timeout", "nan"], "expected seconds"),
    (["workers", "ls", "--timeout", "inf"], "expected seconds"),
    (["watch", "--timeout", "nan"], "expected seconds"),
    (["queue", "show", "r1", "--timeout", "inf"], "expected seconds"),
    (["worker", "--timeout", "nan"], "expected seconds"),
    (["queue", "ls", "--limit", "201"], "expected at most 200"),
    (["queue", "ls", "--connect", "garbage"], "expected PROTOCOL/ADDRESS like tcp/10.0.0.5:7447, found 'garbage'"),
    (["stats", "--connect", "foo/1.2.3.4:7447"], "unknown protocol 'foo'"),
    (["worker", "--connect", "tcp/10.0.0.5"], "expected HOST:PORT after tcp/"),
    (["worker", "--connect", "tcp/[::1]"], "expected HOST:PORT after tcp/"),
    (["stats", "--connect", "tcp/127.0.0.1:\u0667\u0664"], "port must be 0-65535"),
    (["secure", "init", "DATA", "--router-listen", "tls/0.0.0.0"], "expected HOST:PORT after tls/"),
    (["serve", "--listen", "tcp/127.0.0.1:notaport", "--data", "DATA"], "port must be 0-65535, found 'notaport'"),
    (["serve", "--listen", "tcp/127.0.0.1:70000", "--data", "DATA"], "port must be 0-65535, found '70000'"),
    (["router", "--listen", "tls/0.0.0.0"], "expected HOST:PORT after tls/"),
    (["queue", "add", "--shape", "T", "--seed", "-1"], "expected an integer >= 0"),
    (["queue", "add", "--shape", "T", "--idempotency-key", ""], "error: --idempotency-key: expected 1-256 characters"),
    (["queue", "add", "--shape", "T", "--idempotency-key", "k" * 257], "error: --idempotency-key: expected 1-256"),
    (["queue", "add", "--shape", "T", "--priority", "nan"], "expected a finite number"),
    (["queue", "add", "--shape", "T", "--priority", "inf"], "expected a finite number"),
    (["queue", "add", "--shape", "T", "--policy-params", '{"a": NaN}'], "NaN is not a JSON number"),
    (["queue", "add", "--shape", "T", "--policy-params", "[" * 100_000 + "]" * 100_000], "nested too deeply"),
    (["queue", "prioritize", "r1", "nan"], "expected a finite number"),
    (["bench", "loop", "--signal", "total"],
     "error: --signal total ranks by a variance head: it needs --variance-head"),
    (["serve", "--retrain-args", "--from-champion", "--data", "DATA"],
     "argument --retrain-args: expected one argument (a value that starts with '-' needs '=': --retrain-args=VALUE)"),
    (["queue", "prioritize", "r1", "1e13"], "expected a number within ±1e+12, found '1e13'"),
    (["queue", "add", "--shape", "T", "--priority=-2e12"], "expected a number within ±1e+12"),
    (["queue", "add", "--shape", "T", "--max-attempts", "101"], "expected at most 100, found 101"),
    (["queue", "add", "--shape", "T", "--policy-params", '{"sid": "left"}'],
     "--policy-params: policy 'push': unknown parameter(s) ['sid'], "
     "expected ['noise', 'push_steps', 'side', 'stride']"),
    (["queue", "add", "--shape", "T", "--policy", "random_waypoints", "--policy-params", '{"hold": 0}'],
     "--policy-params: policy 'random_waypoints': hold must be in [1, 1000], found 0"),
    (["serve", "--lease-s", "inf", "--data", "DATA"], "argument --lease-s: expected seconds in 0.05..86400, found"),
    (["serve", "--reap-interval-s", "inf", "--data", "DATA"], "--reap-interval-s: expected seconds in 0.01..3600"),
    (["serve", "--seed", "-1", "--data", "DATA"], "expected an integer >= 0"),
    (["serve", "--min-queued", "65", "--data", "DATA"], "--min-queued 65 is above the planner's queue depth cap of 64"),
    (["serve", "--planner", "none", "--min-queued", "3", "--data", "DATA"],
     "--min-queued needs a planner to draw requests from"),
    (["serve", "--planner", "none", "--seed-requests", "5", "--data", "DATA"],
     "--seed-requests needs a planner to draw requests from"),
    (["retrain", "--keep-models", "0", "--data", "DATA"], "expected a positive integer"),
    (["bench", "sim", "--seconds", "inf"], "expected a positive number"),
    (["bench", "dispatch", "--seconds", "inf"], "expected a positive number"),
    (["retrain", "--lr", "inf", "--data", "DATA"], "expected a positive number"),
    (["retrain", "--seed", "-1", "--data", "DATA"], "expected an integer >= 0"),
    (["retrain", "--min-improvement", "2", "--data", "DATA"],
     "argument --min-improvement: expected a fraction in [0, 1)"),
    (["train", "--min-improvement", "1", "--data", "DATA"],
     "argument --min-improvement: expected a fraction in [0, 1)"),
    # a config's own check names the flag, not its field
    (["serve", "--dashboard-port", "-5", "--data", "DATA"], "argument --dashboard-port: expected -1 (none)"),
    (["run", "--dashboard-port", "70000", "--data", "DATA"], "argument --dashboard-port: expected -1 (none)"),
    (["serve", "--retrain-cron", "nope", "--data", "DATA"], "argument --retrain-cron: expected a cron expression"),
    (["serve", "--retrain-cron", "* * * * * *", "--data", "DATA"],  # (croniter's 6th field: seconds)
     "argument --retrain-cron: expected a cron expression of 5 fields"),
    (["serve", "--retrain-cron", "0 0 31 2 *", "--data", "DATA"],
     "argument --retrain-cron: cron '0 0 31 2 *' never fires"),
    (["serve", "--lease-s", "1e6", "--data", "DATA"], "argument --lease-s: expected seconds in 0.05..86400, found"),
    (["serve", "--lease-s", "0", "--data", "DATA"], "argument --lease-s: expected seconds in 0.05..86400, found '0'"),
    (["serve", "--retrain-timeout", "0", "--data", "DATA"], "--retrain-timeout: expected seconds in 1..604800"),
    (["serve", "--namespace", "a*b", "--data", "DATA"], "error: --namespace: expected chunks of"),
    (["stats", "--namespace", "a*b"], "error: --namespace: expected chunks of"),
    (["secure", "init", "DATA", "--namespace", "a*b"], "error: --namespace: expected chunks of"),
    (["bench", "loop", "--budget", "20", "--round", "16"], "need --round >= 1 and --budget >= 2 rounds"),
    (["bench", "score", "--size", "12", "--seconds", "0.1"], "--size must be a multiple of 8"),
    (["score", "e1", "--top", "0", "--data", "DATA"], "argument --top: expected a positive integer, found 0"),
    # too short to learn from: every retrain would fail on them
    (["run", "--steps", "1", "--data", "DATA"], "argument --steps: expected at least 3 steps"),
    (["run", "--steps", "2000", "--data", "DATA"], "argument --steps: expected at most 1000 steps"),
    (["collect", "--steps", "2", "--data", "DATA"], "argument --steps: expected at least 3 steps"),
    (["eval-split", "create", "--episodes", "2", "--steps", "2", "--size", "16", "--data", "DATA"],
     "argument --steps: expected at least 3 steps"),
    (["serve", "--steps", "2", "--data", "DATA"], "argument --steps: expected at least 3 steps"),
    (["queue", "add", "--shape", "T", "--steps", "1"], "argument --steps: expected at least 3 steps"),
    (["bench", "loop", "--steps", "2"], "argument --steps: expected at least 3 steps"),
    (["bench", "loop", "--shape-weights", "T=7,star=1"], "with shapes from T, box, L, disk, found 'star=1'"),
    (["bench", "loop", "--shape-weights", "T"], "expected SHAPE=WEIGHT,..."),
    (["bench", "loop", "--shape-weights", "T=-1,L=2"], "expected a weight >= 0 for T, found '-1'"),
    (["bench", "loop", "--shape-weights", "T=nan"], "weight of T: expected a finite number"),
    (["bench", "loop", "--shape-weights", "T=0,box=0"], "expected at least one positive weight"),
    (["bench", "loop", "--shape-weights", "T=1e308,box=1e308"], "and a finite sum"),
    (["bench", "loop", "--shape-weights", "T=1,T=0"], "T is given twice in 'T=1,T=0'"),
    (["bench", "loop", "--max-shape-share", "0"], "expected a share in (0, 1]"),
    (["bench", "loop", "--progress-floor", "1.5"], "expected a number in [0, 1]"),
    (["bench", "loop", "--shapes-by-progress", "--steps", "6", "--progress-horizon", "5"], "--progress-horizon"),
    (["bench", "loop", "--progress-horizon", "0"], "--progress-horizon"),
    # a TLS listener with no certificate and key to present (Zenoh's own "Missing TLS private key": exit 1)
    (["router", "--listen", "tls/127.0.0.1:7999"], "--listen tls/127.0.0.1:7999: a TLS listener needs a certificate"),
    (["serve", "--listen", "quic/127.0.0.1:7999", "--data", "DATA"], "--listen quic/127.0.0.1:7999: a TLS listener"),
    # a flag that would be silently ignored
    (["bench", "loop", "--progress-floor", "0.5"], "--progress-floor only applies with --shapes-by-progress"),
    (["bench", "loop", "--progress-horizon", "3"], "--progress-horizon only applies with --shapes-by-progress"),
    (["queue", "add", "--shape", "T", "--seed", "0", "--start-state",
      '{"shape": "T", "agent": [100, 100], "object": [256, 256, 0]}'],
     "--seed draws the uniform start state: it does not apply with --start-state"),
    (["bench", "loop", "--palette", "pastel"], "argument --palette: invalid choice"),
    # frames a model cannot train on
    (["run", "--image-size", "12", "--data", "DATA"], "argument --image-size: expected a multiple of 8 from 16"),
    (["bench", "loop", "--image-size", "8"], "argument --image-size: expected a multiple of 8 from 16"),
    (["collect", "--size", "12", "--data", "DATA"], "argument --size: expected a multiple of 8 from 16"),
    (["eval-split", "create", "--size", "8", "--data", "DATA"], "argument --size: expected a multiple of 8 from 16"),
    (["retrain", "--min-improvement", "nan", "--data", "DATA"], "expected a finite number"),
    (["train", "--min-improvement", "inf", "--data", "DATA"], "expected a finite number"),
    (["run", "--seed", "-1", "--data", "DATA"], "expected an integer >= 0"),
    (["serve", "--retrain-threads", "-1", "--data", "DATA"], "argument --retrain-threads: expected an integer >= 0"),
    (["serve", "--scoring-threads", "x", "--data", "DATA"], "argument --scoring-threads: expected an integer"),
    # --retrain-args is checked by the retrain job's parser up front, not at every retrain
    (["run", "--retrain-args=--epochs x", "--data", "DATA"], "argument --epochs: expected a positive integer"),
    (["run", "--retrain-args=--bogus 1", "--data", "DATA"], "unrecognized arguments: --bogus"),
    (["run", "--retrain-args=--data /elsewhere", "--data", "DATA"], "--data is decided by the scheduler"),
    (["run", "--retrain-args=--json", "--data", "DATA"], "--json is decided by the scheduler"),
    (["run", "--retrain-args=--dat /elsewhere", "--data", "DATA"], "--data is decided by the scheduler"),
    # abbreviations the job's own parser finds ambiguous (it also has --data and --wait)
    (["run", "--retrain-args=--d cpu", "--data", "DATA"], "ambiguous option: --d"),
    (["serve", "--retrain-args=--w 8,16,32", "--data", "DATA"], "ambiguous option: --w"),
    (["run", "--retrain-args='unclosed", "--data", "DATA"], "No closing quotation"),
    (["serve", "--retrain-args=--members 0", "--data", "DATA"],
     "argument --members: expected an ensemble of at least 2 members (one cannot disagree), found 0"),
    # an ensemble of one: no disagreement to score by, nan calibration (it was trained and promoted)
    (["train", "--members", "1", "--data", "DATA"], "argument --members: expected an ensemble of at least 2 members"),
    (["retrain", "--members", "1", "--data", "DATA"], "argument --members: expected an ensemble of at least 2"),
    (["run", "--retrain-args=--members 1", "--data", "DATA"], "argument --members: expected an ensemble of at"),
    (["bench", "loop", "--members", "1"], "argument --members: expected an ensemble of at least 2 members"),
    (["bench", "score", "--members", "1"], "argument --members: expected an ensemble of at least 2 members"),
    (["dashboard", "--port", "70000", "--data", "DATA"], "expected a TCP port in 0..65535, found 70000"),
    # a typo that would allocate gigabytes or run for days before anything said so
    (["train", "--members", "500", "--data", "DATA"], "argument --members: expected at most 64 members, found 500"),
    (["run", "--retrain-args=--members 65", "--data", "DATA"], "argument --members: expected at most 64 members"),
    (["bench", "loop", "--widths", "16,32,6400"], "argument --widths: expected channel widths of at most 1024"),
    (["retrain", "--widths", "2000,1,1", "--data", "DATA"], "argument --widths: expected channel widths of at most"),
])
def test_bad_arguments_exit_2_in_one_line(capsys, tmp_path, argv, words) -> None:
    data = tmp_path / "data"
    argv = [str(data) if a == "DATA" else a for a in argv]
    if argv[0] in ("queue", "stats", "workers", "watch", "worker"):
        argv += _connect()  # nobody listens there: an argument that got through would fail with exit 1
    rc, out, err = run_cli(capsys, *argv)
    assert rc == 2 and words in err and err.count("\n") == 1, err
    assert out == "" and not data.exists()


@pytest.mark.parametrize("size", ["8", "12", "20", "1032"])
def test_a_worker_refuses_a_size_no_model_trains_on(capsys, size) -> None:
    """Its size becomes the catalog's when it uploads the first episode. Parsed only: a worker that got
    through would wait for a service for ever."""
    from orchestrator.cli import build_parser
    from workers import cli as agent_cli
    words = f"argument --size: expected a multiple of 8 from 16 to 1024 (what a model trains on), found {size}"
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["worker", "--size", size])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err == f"activecollect worker: error: {words}\n"
    with pytest.raises(SystemExit) as exc:  # python -m workers.agent: the same, in one line too
        agent_cli.main(["--size", size])
    assert exc.value.code == 2 and capsys.readouterr().err == f"python -m workers.agent: error: {words}\n"


@pytest.mark.parametrize("argv, prog", [
    (["retrain", "--retrain-args", "x"], "activecollect retrain"),
    (["models", "show", "m1", "m2"], "activecollect models show"),
    (["queue", "ls", "--frobnicate"], "activecollect queue ls"),
    (["run", "--budget", "4", "extra"], "activecollect run"),
])
def test_an_unknown_argument_is_the_error_of_the_command_given_it(capsys, tmp_path, argv, prog) -> None:
    data = tmp_path / "data"
    rc, out, err = run_cli(capsys, *argv, "--data", str(data)) if argv[0] != "queue" else run_cli(capsys, *argv)
    assert rc == 2 and err.count("\n") == 1 and err.startswith(f"{prog}: error: unrecognized arguments: "), err
    assert out == "" and not data.exists()


def test_retrain_args_are_split_like_a_shell_and_kept_for_the_jobs() -> None:
    args = build_parser().parse_args(["serve", "--retrain-args", "--members 2 --widths '4,4,4' --from-champion"])
    assert args.retrain_args == ("--members", "2", "--widths", "4,4,4", "--from-champion")
    assert build_parser().parse_args(["serve"]).retrain_args == ()  # the job's own defaults
    args = build_parser().parse_args(["serve", "--retrain-args", "--keep-models 3"])
    assert args.retrain_args == ("--keep-models", "3")


def test_retrain_without_a_catalog_is_a_usage_error_and_makes_nothing(capsys, tmp_path) -> None:
    for data in (tmp_path / "missing", tmp_path / "empty"):
        if data.name == "empty":
            data.mkdir()
        rc, _, err = run_cli(capsys, "retrain", "--data", str(data))
        assert rc == 2 and err.count("\n") == 1 and f"no catalog at {data}" in err, err
    assert not (tmp_path / "missing").exists() and list((tmp_path / "empty").iterdir()) == []


def test_retrain_without_train_episodes_fails_in_one_line(capsys, tmp_path) -> None:
    data = tmp_path / "data"
    Catalog(data)
    rc, out, err = run_cli(capsys, "retrain", "--data", str(data), "--members", "2", "--epochs", "1",
                           "--device", "cpu")
    assert rc == 1 and out == "" and err.count("\n") == 1, err
    assert "retrain: failed: " in err and "no train episodes" in err


@pytest.mark.parametrize("text", ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:0", "tcp/[::1]:7447", "tls/host.example:7447",
                                  "udp/10.0.0.5:7447", "quic/10.0.0.5:7447", "ws/10.0.0.5:7448",
                                  "tcp/10.0.0.5:7447#iface=eth0", "tcp/10.0.0.5:7447?prio=1-7",
                                  "unixsock-stream//tmp/zenoh.sock"])
def test_zenoh_endpoints_zenoh_accepts_pass_the_check(text) -> None:
    assert endpoints.endpoint(text) == text



def test_collect_and_run_refuse_another_frame_size_than_the_directory_holds(capsys, tmp_path) -> None:
    data = tmp_path / "data"
    rc, _, err = run_cli(capsys, "collect", "--episodes", "1", "--steps", "3", "--size", "16", "--data", str(data))
    assert rc == 0, err
    files = sorted(p.name for p in data.rglob("*.mcap"))
    for argv, flag in ((["collect", "--episodes", "1", "--steps", "3", "--size", "24"], "--size 16"),
                       (["eval-split", "create", "--episodes", "1", "--steps", "3", "--size", "24"], "--size 16"),
                       (["run", "--budget", "1", "--image-size", "24"], "--image-size 16")):
        rc, out, err = run_cli(capsys, *argv, "--data", str(data))
        assert rc == 2 and err.count("\n") == 1 and "holds 16px episodes" in err and flag in err, err
    assert sorted(p.name for p in data.rglob("*.mcap")) == files


def test_run_refuses_an_eval_split_made_with_other_settings_in_one_line(capsys, tmp_path) -> None:
    from orchestrator.loopconfig import RunConfig
    from workers.collect import create_eval_split
    data = tmp_path / "data"
    create_eval_split(Catalog(data), episodes=2, seed=RunConfig.eval_seed, steps=8, image_size=16)
    rc, out, err = run_cli(capsys, "run", "--budget", "1", "--image-size", "16", "--steps", "8", "--eval-episodes", "3",
                           "--dashboard-port", "-1", "--no-progress", "--data", str(data))
    assert rc == 2 and err.count("\n") == 1, err
    assert (f"{data}'s evaluation split was made with --eval-episodes 2 (this run asks for --eval-episodes 3): "
            "give those, or another --data") in err


def test_run_names_every_flag_a_directory_made_by_other_commands_needs_in_one_line(capsys, tmp_path) -> None:
    """collect + eval-split create made D (their defaults differ from run's): run says at once what to give."""
    data = tmp_path / "data"
    for argv in (["collect", "--episodes", "1", "--steps", "5", "--size", "24"],
                 ["eval-split", "create", "--episodes", "2", "--steps", "6", "--size", "24", "--seed", "7"]):
        rc, _, err = run_cli(capsys, *argv, "--data", str(data))
        assert rc == 0, err
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    rc, out, err = run_cli(capsys, "run", "--budget", "4", "--image-size", "16", "--dashboard-port", "-1",
                           "--no-progress", "--data", str(data))
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert err.startswith(f"activecollect: error: {data}'s evaluation split was made with "), err
    for flag in ("--image-size 24", "--steps 6", "--eval-episodes 2", "--eval-seed 7"):
        assert flag in err.split("(this run asks for")[0], err
    for flag in ("--image-size 16", "--steps 40", "--eval-episodes 16", "--eval-seed 1234"):
        assert flag in err.split("(this run asks for")[1], err
    assert err.rstrip().endswith("give those, or another --data")
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before  # nothing created, nothing collected


def test_run_refuses_a_split_it_cannot_make_in_one_line(capsys, tmp_path) -> None:
    from workers.collect import create_eval_split
    data = tmp_path / "data"
    create_eval_split(Catalog(data), episodes=2, seed=1234, steps=4, image_size=16, random_physics=True)
    rc, out, err = run_cli(capsys, "run", "--budget", "4", "--image-size", "16", "--steps", "4", "--eval-episodes",
                           "2", "--dashboard-port", "-1", "--no-progress", "--data", str(data))
    assert rc == 2 and err.count("\n") == 1, err
    assert "evaluation split was made with random physics, which run does not make: give another --data" in err


def test_serve_takes_no_timeout_it_would_ignore(capsys):
    # The service answers queries and waits on none: --timeout was listed in its help and did nothing.
    rc, _, err = run_cli(capsys, "serve", "--timeout", "3")
    assert rc == 2 and "activecollect serve: error: unrecognized arguments: --timeout 3" in err
    assert "--timeout" not in run_cli(capsys, "serve", "--help")[1]


def test_a_directory_made_at_a_size_or_length_no_flag_accepts_now_is_refused_without_naming_it(tmp_path, capsys,
                                                                                                 monkeypatch):
    # Older versions pinned splits of any size and length: "give --image-size 12" would be refused in turn.
    import numpy as np

    import storage.catalog
    from orchestrator.loopconfig import RunConfig
    from storage.catalog import Catalog
    from workers.collect import collect_episode, create_eval_split
    from workers.env import sample_state
    short = tmp_path / "short"
    create_eval_split(Catalog(short), episodes=2, seed=RunConfig.eval_seed, steps=2, image_size=16)
    rc, _, err = run_cli(capsys, "run", "--data", str(short), "--image-size", "16", "--eval-episodes", "2",
                         "--steps", "8", "--no-progress")
    assert rc == 2 and "made with steps 2, which run does not make: give another --data" in err, err
    small = tmp_path / "small"
    catalog = Catalog(small)
    with monkeypatch.context() as m:  # today's catalog refuses a first episode of 12 px
        m.setattr(storage.catalog, "_check_frame_size", lambda conn, meta: None)
        catalog.add_episode(collect_episode(start_state=sample_state(np.random.default_rng(0), shape="T").to_dict(),
                                            policy="push", seed=0, steps=4, image_size=12))
    rc, _, err = run_cli(capsys, "collect", "--data", str(small), "--size", "16", "--episodes", "1", "--steps", "4")
    assert rc == 2 and "holds 12px episodes, a size no model trains on: give another --data" in err, err
    assert catalog.count() == 1


def test_config_errors_name_flags_but_leave_paths_and_quoted_values_alone():
    from orchestrator.cli.common import config_error
    assert str(config_error(ValueError("need round_episodes >= 1, found round_episodes=16"))) == \
        "need --round >= 1, found --round=16"
    message = "expected an empty directory at /data/image_size, found 'mode' in notes_mode.txt"
    assert str(config_error(ValueError(message), {"image_size": "--size", "mode": "--mode"})) == message


def test_version_prints_the_installed_distributions_version(capsys) -> None:
    import importlib.metadata

    rc, out, err = run_cli(capsys, "--version")
    assert (rc, out, err) == (0, f"activecollect {importlib.metadata.version('activecollect')}\n", "")
