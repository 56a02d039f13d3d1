"""The operator commands (``queue``, ``workers``, ``stats``, ``watch``) and ``serve``'s own flags under hostile
input: each refusal is one line, a bad argument exits 2 before anything is asked, and nothing outlasts its
``--timeout`` without a word."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest

from tests.conftest import run_cli


@pytest.fixture
def frozen_port() -> Iterator[int]:
    """A loopback port whose listener never takes a connection off its backlog, as a stopped (SIGSTOP) or hung
    service's: the kernel completes the TCP handshake and nothing ever answers."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(16)
        yield listener.getsockname()[1]


def _stats_within(capsys, connect: str, namespace: str) -> None:
    """``stats --timeout 1`` says in one line that nobody answered, within a few seconds."""
    started = time.monotonic()
    rc, out, err = run_cli(capsys, "stats", "--connect", connect, "--namespace", namespace, "--timeout", "1")
    took = time.monotonic() - started
    assert rc == 1 and out == "", (rc, out)
    assert err.count("\n") == 1 and "no orchestrator answered" in err and "within 1 s" in err, err
    assert took < 5, f"took {took:.1f} s with --timeout 1"


@pytest.mark.parametrize("proto", ["tcp", "tls"])
def test_a_listener_that_never_answers_ends_within_the_timeout(frozen_port, proto, namespace, capsys) -> None:
    """A frozen service's port: the query ended at --timeout 1, then closing the session waited ~9 s more, saying
    nothing, for Zenoh's handshake to give up on its own 10 s."""
    _stats_within(capsys, f"{proto}/127.0.0.1:{frozen_port}", namespace)


def test_tls_to_a_plain_tcp_service_ends_within_the_timeout(service, port, namespace, capsys) -> None:
    """The wrong protocol to a live service (tls/ where it listens on tcp/): ~10 s for --timeout 1, as above."""
    _stats_within(capsys, f"tls/127.0.0.1:{port}", namespace)


@pytest.mark.parametrize("op", ["show", "cancel", "retry", "prioritize"])
@pytest.mark.parametrize("bad", ["", "d%", "a" * 129, "abc\n", "a b"])
def test_a_malformed_request_id_is_a_usage_error_before_any_service_is_asked(op, bad, endpoint, namespace,
                                                                             capsys) -> None:
    """The service refused it (exit 1, a round trip), and with no service the command waited out --timeout to say
    nobody answered; an id with a trailing newline passed the check (``$`` matches before it)."""
    more = ["1"] if op == "prioritize" else []
    rc, out, err = run_cli(capsys, "queue", op, "--connect", endpoint, "--namespace", namespace, "--timeout", "1",
                           "--", bad, *more)
    assert rc == 2 and out == "", (rc, out)
    assert err.count("\n") == 1 and "argument ID: expected 1-128 characters of [A-Za-z0-9_.-]" in err, err


@pytest.mark.parametrize("command", [["stats"], ["workers", "ls"], ["watch"], ["queue", "ls"]])
def test_a_namespace_with_a_trailing_newline_is_a_usage_error(command, endpoint, capsys) -> None:
    """It passed the check (``$`` matches before a final newline) and the command waited out --timeout for keys
    nobody serves, then said so over two lines."""
    rc, out, err = run_cli(capsys, *command, "--connect", endpoint, "--namespace", "ns\n", "--timeout", "1")
    assert rc == 2 and out == "", (rc, out)
    assert err == "activecollect: error: --namespace: expected chunks of [A-Za-z0-9_-] joined by '/', found 'ns\\n'\n"


@pytest.mark.parametrize("argv", [["serve", "--scoring-threads", "100000"], ["serve", "--retrain-threads", "100000"],
                                  ["serve", "--retrain-args=--threads 100000"], ["retrain", "--threads", "100000"]])
def test_a_torch_thread_count_past_what_torch_can_start_is_a_usage_error(argv, tmp_path, capsys) -> None:
    """serve took 100000 and started; its first scoring (or each retrain job) then died of SIGSEGV in torch's
    thread pool (libgomp "Thread creation failed" at 16384)."""
    rc, out, err = run_cli(capsys, *argv, "--data", str(tmp_path / "none"))
    assert rc == 2 and out == "", (rc, out)
    assert err.count("\n") == 1 and "expected at most 1024 threads, found 100000" in err, err


def test_serve_refuses_a_reap_interval_longer_than_the_lease(tmp_path, capsys) -> None:
    """--lease-s 1 --reap-interval-s 5 started: a lost worker's request stayed out of the queue up to 5 s past
    its 1 s lease. A short --lease-s alone still starts: the default interval is then the lease."""
    data = str(tmp_path / "none")  # (so that a serve the flags let through stops at once, exit 2, saying so)
    rc, out, err = run_cli(capsys, "serve", "--data", data, "--lease-s", "1", "--reap-interval-s", "5")
    assert rc == 2 and out == "", (rc, out)
    assert err == ("activecollect: error: --reap-interval-s 5 is longer than --lease-s 1: an expired lease would "
                   "wait up to 5 s more to go back to the queue; give at most 1\n")
    for flags in (["--lease-s", "0.5"], ["--lease-s", "1", "--reap-interval-s", "1"]):
        rc, _, err = run_cli(capsys, "serve", "--data", data, *flags)
        assert rc == 2 and "no data directory at" in err, err


def test_a_repeated_add_says_when_its_priority_is_not_the_one_asked_for(service, endpoint, namespace, capsys) -> None:
    """The same --idempotency-key with another --priority returned the first request (a priority is no part of
    the ask: `queue prioritize` changes it) and printed its priority, 0, with no word that 5 was not set."""
    add = ("queue", "add", "--shape", "T", "--idempotency-key", "k1", "--connect", endpoint, "--namespace", namespace)
    rc, out, _ = run_cli(capsys, *add)
    assert rc == 0 and "its priority stays" not in out, out
    request_id = service.queue.list()[0].id
    rc, out, _ = run_cli(capsys, *add, "--priority", "5")
    assert rc == 0 and out.startswith("already queued (same idempotency key)"), out
    assert f"its priority stays 0, not --priority 5: `queue prioritize {request_id} 5` sets it" in out, out
    assert [r.priority for r in service.queue.list()] == [0.0]
    rc, out, _ = run_cli(capsys, *add)  # the same ask again: nothing to say
    assert rc == 0 and "its priority stays" not in out, out
