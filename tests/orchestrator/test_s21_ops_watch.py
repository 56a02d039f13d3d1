"""``activecollect watch`` across a service restart: it says when the service goes and when it is back."""

from __future__ import annotations

from tests.conftest import run_cli, wait_for


def test_watch_says_when_the_service_goes_away_and_follows_the_next_one(spawn, spawn_service, endpoint, namespace,
                                                                        capsys) -> None:
    """From the events alone a service that stopped looked like a quiet one: watch printed nothing, for ever."""
    connection = ("--connect", endpoint, "--namespace", namespace)
    service = spawn_service()
    wait_for(lambda: run_cli(capsys, "stats", *connection, "--timeout", "1")[0] == 0, timeout=60,
             message="the service to answer")
    watch = spawn("watch", "watch", *connection, "--timeout", "30")
    wait_for(lambda: "watching" in watch.log(), timeout=60, message="watch to start")
    assert service.stop() == 0
    wait_for(lambda: "no service answers" in watch.log(), timeout=30, message="watch to say the service went away")
    assert watch.alive(), "watch keeps watching for the next service"
    spawn_service(name="service-again")
    wait_for(lambda: "answers on" in watch.log().split("no service answers", 1)[1], timeout=60,
             message="watch to say a service is back")
    rc, out, _ = run_cli(capsys, "queue", "add", "--shape", "T", *connection, "--timeout", "30")
    assert rc == 0, out
    wait_for(lambda: "request.queued" in watch.log(), timeout=30, message="the next service's event")
    lines = watch.log().splitlines()
    assert sum("no service answers" in line for line in lines) == 1, lines
    assert sum(line.startswith("# a service answers") for line in lines) == 1, lines
