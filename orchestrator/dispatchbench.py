"""``activecollect bench dispatch``: how fast the service hands out and takes back work.

Three phases with ``workers`` concurrent client threads in this process
talking to a server in a child process over loopback TCP (peer mode), and one
in-process phase without Zenoh:

1. ``raw``: a bare Zenoh queryable that echoes its payload -- the floor any
   query-based dispatch pays. Client payload: a LeaseRequest's bytes.
2. ``dispatch``: the real ``Service`` (real SQLite queue, WAL). Each cycle is
   ``lease`` then ``fail`` -- the lease-ending transaction with the same fencing
   check as ``complete``, without an episode, so the request goes back to the
   queue and is leased again (requests get the maximum attempts). This is the
   dispatch path alone: two queries, two ``BEGIN IMMEDIATE`` transactions.
3. ``upload``: the full worker path on the real ``Service``: ``lease`` then
   ``upload`` of a tiny pre-encoded MCAP episode (2 steps of 8x8 frames, made
   before the clock starts) -- verify, write + fsync, index and complete in one
   transaction. Bounded by MCAP verification and fsync, not by dispatch.
4. ``queue``: ``RequestQueue.lease`` then ``RequestQueue.complete`` in this
   process, one thread, on a fresh queue file set up as the service sets it up
   (WAL, background checkpoints); each request is leased once and ends ``done``.
   No Zenoh, no episode file: the SQLite floor of a cycle that ends in
   ``complete``, the transition the wire only reaches through an upload.

How far ``dispatch`` stands in for real dispatch: a worker's cycle is lease ->
(renews) -> upload, and both lease-ending transactions are one ``UPDATE`` with
the same fencing ``WHERE`` and one commit, so ``fail`` costs the queue what
``complete`` does (``queue`` shows the two side by side); what it leaves out is
the episode itself (``upload``). Each cycle is two round trips and is counted
once. The clients share one process and one Zenoh session, where real workers
each have their own, so on a small machine they take CPU from the server.

``raw`` and ``dispatch`` run in alternating slices (``rounds`` of each, both
servers up throughout) so that on a shared machine, whose load changes from one
second to the next, the two phases whose p99s are compared see the same load.

Latencies are per query (lease, fail, upload) and per cycle; throughput is
cycles per second over all clients.
"""

from __future__ import annotations

import argparse
import socket
import os
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from orchestrator import messages, protocol, transport
from orchestrator.protocol import Keys
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
from storage.catalog import Catalog
from storage.episodes import encode_episode
from storage.queue import RequestQueue
from storage.requests import NewRequest
from storage.records import MIN_TRAINABLE_SIZE, Episode, EpisodeMeta

_START = {"shape": "box", "agent": [100.0, 100.0], "agent_vel": [0.0, 0.0], "object": [256.0, 256.0, 0.0],
          "object_vel": [0.0, 0.0, 0.0], "physics": {"mass": 1.0, "friction": 0.6, "ground_friction": 1.0}}


#: The most concurrent clients: the upload phase encodes ``upload_requests`` episodes per client before its clock
#: starts (~0.3 ms and ~4 kB each: 1500 per client, ~30 s and ~400 MB at 64 clients).
MAX_WORKERS = 64


@dataclass
class BenchConfig:
    """What ``bench dispatch`` measures."""

    workers: int = 8
    """Concurrent client threads."""
    seconds: float = 5.0
    """Measuring time of each phase."""
    data_dir: Path | None = None
    """Data directory of the benchmark service (default: a fresh temporary one)."""
    dispatch_requests: int = 1000
    """Requests in the queue for the dispatch phase (each can be leased up to MAX_ATTEMPTS times)."""
    upload_requests: int = 1500
    """Requests (and pre-encoded episodes) for the upload phase; the phase ends early when they run out."""
    queue_requests: int = 20000
    """Requests for the in-process queue phase; it ends early when they are all done."""
    lease_s: float = 60.0
    """Lease length the benchmark service hands out."""
    rounds: int = 3
    """Slices the raw and dispatch phases alternate in (seconds / rounds each)."""

    def __post_init__(self) -> None:
        if not 1 <= self.workers <= MAX_WORKERS or not self.seconds > 0 or self.rounds < 1:
            raise ValueError(f"workers must be in 1..{MAX_WORKERS}, rounds >= 1 and seconds > 0, found "
                             f"{self.workers}, {self.rounds} and {self.seconds}")


# --- the server side (child process) ---------------------------------------------------------------

def _serve_echo(listen: str, key: str) -> None:
    session = transport.open_session(listen=[listen])
    try:
        queryable = session.declare_queryable(key, lambda q: q.reply(key, q.payload.to_bytes() if q.payload else b""))
        _ready_and_wait()
        queryable.undeclare()
    finally:
        session.close()  # an open session's threads would keep the process from exiting


def _serve_service(listen: str, namespace: str, data_dir: str, lease_s: float) -> None:
    service = Service(ServiceConfig(data_dir=Path(data_dir), namespace=namespace, listen=(listen,),
                                    lease_s=lease_s, reap_interval_s=5.0))
    service.start()
    try:
        _ready_and_wait()
    finally:
        service.stop()  # its threads would keep the process from exiting


def _ready_and_wait() -> None:
    try:
        print("ready", flush=True)
    except BrokenPipeError:  # the parent went away while we started
        return
    sys.stdin.read()  # the parent closes our stdin to stop us


class _Child:
    """A server role of this module in a child process; ``stop()`` closes its stdin and waits."""

    def __init__(self, *role_args: str, timeout: float = 60.0) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # A process group of its own: a terminal's Ctrl-C, sent to our group, is ours to handle; the child stops
        # when we close its stdin (or die). Taken as a KeyboardInterrupt there, it would end the role before its
        # session or service closed, and their threads would keep the child alive, ours waiting on it.
        self.popen = subprocess.Popen([sys.executable, "-m", "orchestrator.dispatchbench", *role_args],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env, text=True,
                                      process_group=0)
        try:
            line = _readline(self.popen, timeout)
        except BaseException:  # Ctrl-C while it starts: stop it before unwinding
            self.stop()
            raise
        if line.strip() != "ready":
            self.stop()
            raise RuntimeError(f"benchmark server {role_args[0]} did not start (said {line!r})")

    def stop(self) -> None:
        if self.popen.stdin is not None:
            self.popen.stdin.close()
        try:
            self.popen.wait(30)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait()


def _readline(popen: subprocess.Popen, timeout: float) -> str:
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.append(popen.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return out[0] if out else ""


# --- the client side -------------------------------------------------------------------------------

def _percentiles(samples: list[float]) -> dict[str, float]:
    if not samples:
        return {"n": 0}
    a = np.asarray(samples) * 1e3  # ms
    return {"n": int(a.size), "p50_ms": round(float(np.percentile(a, 50)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "max_ms": round(float(a.max()), 3)}


Cycle = Callable[[zenoh.Session, int, dict[str, list[float]]], bool]


@dataclass
class _Slice:
    """What one ``_drive`` measured: cycles, wall time and every latency sample."""

    cycles: int
    seconds: float
    samples: dict[str, list[float]]


def _drive(workers: int, seconds: float, cycle: Cycle, session: zenoh.Session) -> _Slice:
    """Run ``cycle(session, worker_index, latencies)`` in ``workers`` threads for ``seconds``.

    ``cycle`` returns False when it has nothing more to do.
    """
    lats: list[dict[str, list[float]]] = [{} for _ in range(workers)]
    counts = [0] * workers
    deadline = time.perf_counter() + seconds
    stop = threading.Event()

    def loop(i: int) -> None:
        while time.perf_counter() < deadline and not stop.is_set():
            if not cycle(session, i, lats[i]):
                return
            counts[i] += 1

    threads = [threading.Thread(target=loop, args=(i,)) for i in range(workers)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    try:
        for t in threads:
            t.join()
    except BaseException:  # Ctrl-C: let each client finish its cycle before the caller closes the session
        stop.set()
        for t in threads:
            t.join()
        raise
    merged: dict[str, list[float]] = {}
    for per_thread in lats:
        for name, values in per_thread.items():
            merged.setdefault(name, []).extend(values)
    return _Slice(sum(counts), time.perf_counter() - start, merged)


def _summary(slices: list[_Slice]) -> dict[str, Any]:
    """Cycles/s and latency percentiles over all the slices of one phase."""
    cycles, seconds = sum(s.cycles for s in slices), sum(s.seconds for s in slices)
    merged: dict[str, list[float]] = {}
    for sl in slices:
        for name, values in sl.samples.items():
            merged.setdefault(name, []).extend(values)
    return {"cycles": cycles, "seconds": round(seconds, 3), "cycles_per_s": round(cycles / seconds, 1),
            "rounds": len(slices), "latency": {name: _percentiles(v) for name, v in sorted(merged.items())}}


def _timed(lats: dict[str, list[float]], name: str, fn: Callable[[], bytes]) -> bytes:
    t0 = time.perf_counter()
    out = fn()
    lats.setdefault(name, []).append(time.perf_counter() - t0)
    return out


@contextmanager
def _raw_server(endpoint: str) -> Iterator[tuple[zenoh.Session, Cycle]]:
    """An echo server in a child process and a connected client: (session, one query cycle)."""
    key = "bench/echo"
    child = _Child("echo", "--listen", endpoint, "--key", key)
    session = transport.open_session(connect=[endpoint])
    try:
        payload = messages.LeaseRequest(worker_id="bench-0").to_json()
        transport.query(session, key, payload, timeout=30)  # connected and routed before the clock starts

        def cycle(s: zenoh.Session, i: int, lats: dict[str, list[float]]) -> bool:
            _timed(lats, "query", lambda: transport.query(s, key, payload, timeout=10))
            return True

        yield session, cycle
    finally:
        session.close()
        child.stop()


def _tiny_episode(request_id: str, worker_id: str, token: int = 1) -> bytes:
    size = MIN_TRAINABLE_SIZE  # the first upload fixes the catalog's frame size: the smallest one it takes
    meta = EpisodeMeta(episode_id=uuid.uuid4().hex, task="push", shape="box", physics=dict(_START["physics"]),
                       seed=messages.request_seed(request_id, token), policy="push", start_state=dict(_START),
                       image_size=size, request_id=request_id, worker_id=worker_id)
    return encode_episode(Episode(meta, np.zeros((2, size, size, 3), np.uint8), np.zeros((2, 2), np.float32),
                                  np.zeros((2, 11), np.float64)))


def _fill(data_dir: Path, n: int, max_attempts: int) -> list[str]:
    """Enqueue ``n`` requests directly in the service's database (before it starts); their ids."""
    catalog = Catalog(data_dir)
    with RequestQueue(catalog.db_path) as queue:
        news = [NewRequest(task="push", shape="box", start_state=dict(_START), steps=2, max_attempts=max_attempts)
                for _ in range(n)]
        return [r.id for r, _ in queue.enqueue_many(news)]


def _lease(s: zenoh.Session, keys: Keys, msg: bytes, lats: dict[str, list[float]]) -> dict[str, Any] | None:
    try:
        body = protocol.parse_reply(_timed(lats, "lease", lambda: transport.query(s, keys.lease, msg, timeout=10)))
    except protocol.ProtocolError as exc:
        if exc.code == protocol.ErrorCode.NO_WORK:
            return None
        raise
    return body["grant"]


@contextmanager
def _service(cfg: BenchConfig, endpoint: str, namespace: str, data_dir: Path) -> Iterator[tuple[zenoh.Session, Keys]]:
    """The real service in a child process over ``data_dir``, and a client session that it answers."""
    keys = Keys(namespace)
    child = _Child("service", "--listen", endpoint, "--namespace", namespace, "--data", str(data_dir),
                   "--lease-s", str(cfg.lease_s))
    session = transport.open_session(connect=[endpoint])
    try:
        transport.query(session, keys.admin("stats"), timeout=30)
        yield session, keys
    finally:
        session.close()
        child.stop()


#: What a cycle does with a grant: (session, worker index, grant, latencies) -> None.
AfterLease = Callable[[zenoh.Session, int, dict[str, Any], dict[str, list[float]]], None]


def _lease_cycle(cfg: BenchConfig, keys: Keys, after: AfterLease) -> Cycle:
    """One timed cycle per call: lease as worker ``bench-i``, then ``after``; False when the queue is empty."""
    lease_msgs = [messages.LeaseRequest(worker_id=f"bench-{i}").to_json() for i in range(cfg.workers)]

    def cycle(s: zenoh.Session, i: int, lats: dict[str, list[float]]) -> bool:
        t0 = time.perf_counter()
        grant = _lease(s, keys, lease_msgs[i], lats)
        if grant is None:
            return False
        after(s, i, grant, lats)
        lats.setdefault("cycle", []).append(time.perf_counter() - t0)
        return True

    return cycle


@contextmanager
def _dispatch_server(cfg: BenchConfig, endpoint: str, data_dir: Path) -> Iterator[tuple[zenoh.Session, Cycle]]:
    """The real service in a child process and a connected client: (session, one lease -> fail cycle)."""
    _fill(data_dir, cfg.dispatch_requests, protocol.MAX_ATTEMPTS)
    with _service(cfg, endpoint, "bench", data_dir) as (session, keys):
        def give_back(s: zenoh.Session, i: int, grant: dict[str, Any], lats: dict[str, list[float]]) -> None:
            msg = messages.FailRequest(request_id=grant["request_id"], token=grant["token"],
                                       worker_id=f"bench-{i}", error="bench: give back").to_json()
            protocol.parse_reply(_timed(lats, "fail", lambda: transport.query(s, keys.fail, msg, timeout=10)))

        yield session, _lease_cycle(cfg, keys, give_back)


def _phases_raw_and_dispatch(cfg: BenchConfig, data_dir: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Both servers up; raw and dispatch slices alternate ``cfg.rounds`` times."""
    raw_slices: list[_Slice] = []
    dispatch_slices: list[_Slice] = []
    with _raw_server(f"tcp/127.0.0.1:{_free_port()}") as (raw_session, raw_cycle), \
            _dispatch_server(cfg, f"tcp/127.0.0.1:{_free_port()}", data_dir) as (dispatch_session, dispatch_cycle):
        for _ in range(cfg.rounds):
            raw_slices.append(_drive(cfg.workers, cfg.seconds / cfg.rounds, raw_cycle, raw_session))
            dispatch_slices.append(_drive(cfg.workers, cfg.seconds / cfg.rounds, dispatch_cycle, dispatch_session))
    return _summary(raw_slices), _summary(dispatch_slices)


def _phase_upload(cfg: BenchConfig, endpoint: str, data_dir: Path) -> dict[str, Any]:
    ids = _fill(data_dir, cfg.upload_requests, 3)
    # Encoded before the clock starts, for whichever worker leases the request (the service checks the upload
    # names the worker that holds the lease, and the first lease's seed).
    episodes = {(rid, i): _tiny_episode(rid, f"bench-{i}") for rid in ids for i in range(cfg.workers)}
    with _service(cfg, endpoint, "benchup", data_dir) as (session, keys):
        def upload(s: zenoh.Session, i: int, grant: dict[str, Any], lats: dict[str, list[float]]) -> None:
            data = (episodes[grant["request_id"], i] if grant["token"] == 1
                    else _tiny_episode(grant["request_id"], f"bench-{i}", grant["token"]))
            header = messages.UploadHeader.for_payload(data, request_id=grant["request_id"], token=grant["token"],
                                                       worker_id=f"bench-{i}").to_json()
            protocol.parse_reply(_timed(lats, "upload",
                                        lambda: transport.query(s, keys.upload, data, header, timeout=30)))

        result = _summary([_drive(cfg.workers, cfg.seconds, _lease_cycle(cfg, keys, upload), session)])
        result["episode_bytes"] = len(next(iter(episodes.values())))
        return result


def _phase_queue(cfg: BenchConfig, data_dir: Path) -> dict[str, Any]:
    """lease -> complete and lease -> fail on the queue itself, one thread, no Zenoh."""
    _fill(data_dir, cfg.queue_requests, protocol.MAX_ATTEMPTS)
    out: dict[str, Any] = {}
    with RequestQueue(Catalog(data_dir).db_path, background_checkpoint=True) as queue:
        for name in ("lease_fail", "lease_complete"):
            lats: dict[str, list[float]] = {}
            cycles, deadline = 0, time.perf_counter() + cfg.seconds / 2
            start = time.perf_counter()
            while time.perf_counter() < deadline:
                t0 = time.perf_counter()
                lease = queue.lease("bench", lease_s=cfg.lease_s)
                if lease is None:
                    break
                if name == "lease_fail":
                    queue.fail(lease.request.id, lease.token, "bench: give back", worker_id="bench")
                else:
                    queue.complete(lease.request.id, lease.token, uuid.uuid4().hex, worker_id="bench")
                lats.setdefault("cycle", []).append(time.perf_counter() - t0)
                cycles += 1
            elapsed = time.perf_counter() - start
            out[name] = {"cycles": cycles, "seconds": round(elapsed, 3), "cycles_per_s": round(cycles / elapsed, 1),
                         "latency": {k: _percentiles(v) for k, v in lats.items()}}
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(cfg: BenchConfig) -> dict[str, Any]:
    """Run the phases; a JSON-able result with the goal checks."""
    with tempfile.TemporaryDirectory(prefix="activecollect-dispatch-") as tmp:
        base = Path(cfg.data_dir) if cfg.data_dir is not None else Path(tmp)
        raw, dispatch = _phases_raw_and_dispatch(cfg, base / "dispatch")
        upload = _phase_upload(cfg, f"tcp/127.0.0.1:{_free_port()}", base / "upload")
        queue = _phase_queue(cfg, base / "queue")
    # (a phase too short for one cycle to finish has no latency to compare: the ratio is None)
    raw_p99 = raw["latency"].get("query", {}).get("p99_ms")
    lease_p99 = dispatch["latency"].get("lease", {}).get("p99_ms")
    return {
        "workers": cfg.workers, "seconds_per_phase": cfg.seconds, "cpus": os.cpu_count(),
        "raw_zenoh": raw, "dispatch_lease_fail": dispatch, "upload_lease_upload": upload,
        "queue_in_process": queue,
        "goals": {
            "lease_round_trips_per_s": dispatch["cycles_per_s"], "lease_round_trips_goal": 2000,
            "lease_p99_over_raw_p99": round(lease_p99 / raw_p99, 2) if raw_p99 and lease_p99 is not None else None,
            "p99_ratio_goal": 5.0,
        },
    }


def format_result(r: dict[str, Any]) -> str:
    """Human-readable summary of :func:`run`'s result."""
    lines = [f"dispatch benchmark: {r['workers']} clients, {r['seconds_per_phase']:g} s per phase, {r['cpus']} CPUs"]
    for name, label in (("raw_zenoh", "raw Zenoh echo query"), ("dispatch_lease_fail", "lease -> fail (dispatch)"),
                        ("upload_lease_upload", "lease -> upload (tiny MCAP)")):
        phase = r[name]
        lat = "  ".join(f"{k} p50 {v['p50_ms']:.3f} ms p99 {v['p99_ms']:.3f} ms"
                        for k, v in phase["latency"].items() if v.get("n"))
        lines.append(f"  {label:30} {phase['cycles_per_s']:9.1f} /s   {lat}")
    for name, phase in r["queue_in_process"].items():
        cyc = phase["latency"].get("cycle", {})
        lat = f"cycle p50 {cyc['p50_ms']:.3f} ms p99 {cyc['p99_ms']:.3f} ms" if cyc.get("n") else ""
        label = f"in-process {name.replace('_', ' -> ')}"
        lines.append(f"  {label:30} {phase['cycles_per_s']:9.1f} /s   {lat}")
    g = r["goals"]
    ratio = g["lease_p99_over_raw_p99"]
    ratio_text = "not measured (no query finished in time)" if ratio is None else f"= {ratio}x raw p99"
    lines.append(f"  goals: {g['lease_round_trips_per_s']:.0f} lease round trips/s (goal >= "
                 f"{g['lease_round_trips_goal']}), lease p99 {ratio_text} (goal <= {g['p99_ratio_goal']:g}x)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Child-process roles: ``echo`` and ``service`` (used by :func:`run`)."""
    parser = argparse.ArgumentParser(prog="python -m orchestrator.dispatchbench")
    parser.add_argument("role", choices=("echo", "service"))
    parser.add_argument("--listen", required=True)
    parser.add_argument("--key", default="bench/echo")
    parser.add_argument("--namespace", default="bench")
    parser.add_argument("--data", default=None)
    parser.add_argument("--lease-s", type=float, default=60.0)
    args = parser.parse_args(argv)
    if args.role == "echo":
        _serve_echo(args.listen, args.key)
    else:
        _serve_service(args.listen, args.namespace, args.data, args.lease_s)


if __name__ == "__main__":
    main()
