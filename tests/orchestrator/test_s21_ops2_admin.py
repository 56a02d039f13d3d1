"""``workers.ls`` fits in one reply however many workers there are, as ``queue.ls`` and ``models.ls`` do: those
holding leases are kept first, the reply says it was cut and of how many, and so does the CLI."""

from __future__ import annotations

import json
from pathlib import Path

from orchestrator import admin, protocol, transport
from orchestrator.cli import main
from orchestrator.protocol import Keys
from storage.queue import RequestQueue
from storage.requests import NewRequest

START = {"shape": "box", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.3]}
#: Worker ids as long as the protocol allows (128 characters): about 1,400 rows fill a reply.
WORKERS = 1_600


def worker_id(i: int, prefix: str = "w") -> str:
    return f"{prefix}{i:05d}".ljust(128, "x")


def hold_leases(queue: RequestQueue, ids: list[str]) -> dict[str, str]:
    """One lease for each worker of ``ids``: {worker id: request id}."""
    queue.enqueue_many([NewRequest(task="push", shape="box", start_state=START) for _ in ids])
    return {w: queue.lease(w).request.id for w in ids}


def test_workers_ls_of_many_workers_fits_in_one_reply_leaseholders_first(tmp_path: Path) -> None:
    alive = [worker_id(i) for i in range(WORKERS)]
    ghosts = [worker_id(i, "z-ghost") for i in range(3)]  # dead, holding leases nobody renews: sorted last
    with RequestQueue(tmp_path / "catalog.sqlite") as queue:
        held = hold_leases(queue, [alive[0], alive[-1], *ghosts])
        body = admin.handle("workers.ls", queue=queue, workers=lambda: alive)
        reply = admin.serve(b"", op="workers.ls", queue=queue, workers=lambda: alive)
    assert len(reply) <= protocol.MAX_MESSAGE_BYTES and protocol.parse_reply(reply) == body  # too_large before
    assert body["truncated"] is True and body["total"] == WORKERS + len(ghosts)
    rows = body["workers"]
    assert 1_000 < len(rows) < WORKERS and [r["id"] for r in rows] == sorted(r["id"] for r in rows)
    shown = {r["id"]: r for r in rows}
    for w, request_id in held.items():  # every leaseholder, alive or not, whatever its place by id
        assert shown[w]["leases"] == [request_id] and shown[w]["alive"] == (w in alive), w
    idle = [r["id"] for r in rows if not r["leases"]]
    assert idle == sorted(set(alive) - set(held))[:len(idle)]  # then the others, by id


def test_a_short_workers_ls_says_it_is_whole(tmp_path: Path) -> None:
    with RequestQueue(tmp_path / "catalog.sqlite") as queue:
        body = admin.handle("workers.ls", queue=queue, workers=lambda: ["w2", "w1"])
    assert body == {"workers": [{"id": "w1", "alive": True, "leases": []}, {"id": "w2", "alive": True, "leases": []}],
                    "truncated": False, "total": 2}


def test_workers_ls_over_zenoh_fits_and_the_cli_says_it_was_cut(service, client, endpoint, namespace,
                                                                capsys) -> None:
    """Workers gone with their leases still held (not reaped yet) are listed as well as live ones."""
    ghosts = [worker_id(i, "ghost") for i in range(WORKERS)]
    hold_leases(service.queue, ghosts)
    reply = transport.query(client, Keys(namespace).admin("workers.ls"), b"", timeout=10)
    body = protocol.parse_reply(reply)  # refused as too_large before
    assert body["truncated"] is True and body["total"] == WORKERS and 0 < len(body["workers"]) < WORKERS

    argv = ["workers", "ls", "--connect", endpoint, "--namespace", namespace, "--timeout", "10"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"list cut at {len(body['workers'])} of {WORKERS} workers to fit in one reply" in out, out[-400:]
    assert main([*argv, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["truncated"] is True
