"""dashboard, backup and the benchmarks (``bench ...``, ``python -m bench``) under an operator's hostile input:
empty values (an unset shell variable), numbers past what a run can do, an output directory that holds other
files. Each is refused in one line, exit 2, before anything is done."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bench.__main__ as bench_main
from orchestrator.cli import build_parser
from storage.catalog import Catalog
from tests.conftest import run_cli
from tests.storage.test_episodes import make_episode


def _one_line(err: str) -> bool:
    return err.count("\n") == 1 and "Traceback" not in err


def _refused_by_the_parser(capsys, *argv: str) -> str:
    """The one line argparse wrote refusing ``argv`` (exit 2), checked without running the command: on a
    command that took the value, running it would serve forever or crash the test's process."""
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(list(argv))
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "" and _one_line(err), err
    return err


def test_backup_to_an_empty_dest_is_a_usage_error_not_this_directory(capsys, monkeypatch, tmp_path, data_dir):
    """`backup "$DEST"` with DEST unset, in an empty directory: it backed the data up into the current directory
    (and replaced that directory under the shell's feet)."""
    Catalog(data_dir).add_episode(make_episode(np.random.default_rng(3)))
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    rc, out, err = run_cli(capsys, "backup", "", "--data", str(data_dir))
    assert rc == 2 and out == "" and _one_line(err), err
    assert "argument DEST: expected a path, found an empty path" in err
    assert list(here.iterdir()) == []


@pytest.mark.parametrize("host", ["", " "])
def test_dashboard_on_an_empty_host_is_a_usage_error_not_every_interface(capsys, data_dir, host):
    """An empty --host (an unset $HOST) bound 0.0.0.0: the unauthenticated dashboard on every interface."""
    err = _refused_by_the_parser(capsys, "dashboard", "--data", str(data_dir), "--host", host)
    assert "argument --host: expected an address to bind such as 127.0.0.1" in err and "0.0.0.0" in err


@pytest.mark.parametrize("threads", ["1025", "99999999", str(10**20)])
def test_bench_score_threads_past_what_torch_takes_is_a_usage_error(capsys, threads):
    """torch crashed (SIGSEGV) at its first product with 99999999 threads, as the other --threads flags did."""
    err = _refused_by_the_parser(capsys, "bench", "score", "--threads", threads)
    assert "argument --threads: expected at most 1024 threads" in err


def test_bench_score_threads_zero_is_torchs_own():
    args = build_parser().parse_args(["bench", "score", "--threads", "0"])
    assert args.threads == 0


@pytest.mark.parametrize("workers", ["65", str(10**20)])
def test_bench_dispatch_with_more_clients_than_it_can_prepare_is_a_usage_error(capsys, workers):
    """10^20 clients hung (a list per client, 1500 episodes encoded per client) once its servers had started."""
    err = _refused_by_the_parser(capsys, "bench", "dispatch", "--workers", workers)
    assert "argument --workers: expected at most 64 clients" in err


def test_bench_dispatch_too_short_to_finish_a_query_prints_valid_json(capsys):
    """--seconds 1e-300: no query finished in any phase, and the goals' p99 ratio was a KeyError traceback."""
    rc, out, err = run_cli(capsys, "bench", "dispatch", "--workers", "1", "--seconds", "1e-300", "--json")
    assert rc == 0 and "Traceback" not in err, err
    result = json.loads(out, parse_constant=lambda c: pytest.fail(f"not strict JSON: {c}"))
    assert result["goals"]["lease_p99_over_raw_p99"] is None
    assert result["raw_zenoh"]["cycles"] == result["dispatch_lease_fail"]["cycles"] == 0


@pytest.mark.parametrize("seeds", ["1001", str(10**20)])
def test_bench_loop_with_more_seeds_than_a_run_can_do_is_a_usage_error(capsys, seeds):
    """10^20 seeds was an OverflowError traceback (range to a tuple), 10^10 a hang listing them."""
    err = _refused_by_the_parser(capsys, "bench", "loop", "--seeds", seeds)
    assert "argument --seeds: expected at most 1000 seeds" in err


def test_bench_loop_into_a_directory_that_holds_other_files_is_refused(capsys, data_dir):
    """--out DATA (a data directory, a home): the run wrote its config.json, summary.json, loop.png and seed*/
    among the files there, replacing any of those names."""
    Catalog(data_dir)
    (data_dir / "config.json").write_text('{"mine": true}')
    before = sorted(data_dir.rglob("*"))
    rc, out, err = run_cli(capsys, "bench", "loop", "--seeds", "1", "--budget", "2", "--round", "1", "--steps", "8",
                           "--image-size", "16", "--epochs", "1", "--members", "2", "--device", "cpu",
                           "--out", str(data_dir))
    assert rc == 2 and out == "" and _one_line(err), err
    assert f"{data_dir} is not empty (it holds catalog.sqlite" in err and "give a new or empty --out" in err
    assert sorted(data_dir.rglob("*")) == before and (data_dir / "config.json").read_text() == '{"mine": true}'


@pytest.mark.parametrize("only, said", [("", "--only names no benchmark, found ''"),
                                        (" , ", "--only names no benchmark, found ' , '"),
                                        ("score,dispatch,score", "--only names score twice")])
def test_make_bench_only_naming_nothing_or_one_twice_is_a_usage_error(capsys, monkeypatch, tmp_path, only, said):
    """`make bench ARGS="--only $ONLY"` with ONLY unset ran nothing and wrote a results file, exit 0; a name given
    twice ran twice, its second figures replacing the first's."""
    monkeypatch.setattr(bench_main, "HERE", tmp_path)  # (where its results/ would go)
    monkeypatch.setattr(bench_main, "BENCHES", {name: [bench_main.PY, "-c", "print('{}')"]
                                                for name in bench_main.BENCHES})
    with pytest.raises(SystemExit) as exc:
        bench_main.main(["--only", only])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "" and _one_line(err), err
    assert err.startswith("python -m bench: error: ") and said in err
    assert list(tmp_path.iterdir()) == []
