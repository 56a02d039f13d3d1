"""Partition tests: two network namespaces joined by a veth pair, the link cut and restored.

Namespace A (10.231.0.1) holds the router and the orchestrator, namespace B (10.231.0.2)
a worker; the addresses exist only between these two namespaces. Needs root and `ip netns`;
skips with the reason otherwise. Namespaces are removed in a finally, whatever happens.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import json5
import numpy as np
import pytest

from orchestrator.secure import SecureInitConfig, SecureSet, init_secure
from storage.catalog import Catalog
from storage.queue import RequestQueue
from storage.requests import NewRequest, RequestStatus
from workers.env import sample_state
from workers.upload import DEFAULT_PART_KB
from tests.orchestrator.test_secure import Proc, start_router, stays_false
from tests.conftest import holds, wait_for

ADDR_A, ADDR_B = "10.231.0.1", "10.231.0.2"
PORT = 7447  # free by construction: namespace A is new and empty
NS = "activecollect"
#: Zenoh's link lease for these tests (ms): a cut link is noticed in about this long.
LINK_LEASE_MS = 2000


def _netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "partition tests need root (network namespaces and veth pairs)"
    if shutil.which("ip") is None:
        return "partition tests need iproute2's `ip` command"
    probe = f"ac-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` is not permitted here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


_REASON = _netns_unavailable()
pytestmark = pytest.mark.skipif(_REASON is not None, reason=_REASON or "")


@dataclass
class NetnsPair:
    """Two namespaces, ``a`` and ``b``, joined by veth ``ac-a`` (ADDR_A) <-> ``ac-b`` (ADDR_B)."""

    a: str
    b: str

    def exec_prefix(self, ns: str) -> tuple[str, ...]:
        return ("ip", "netns", "exec", ns)

    def link(self, up: bool) -> None:
        """Cuts (or restores) the wire by taking B's end of the pair down (or up)."""
        _ip("-n", self.b, "link", "set", "ac-b", "up" if up else "down")

    def throttle(self, rate: str) -> None:
        """Slows B's uplink (what B sends) to ``rate`` (tc's words: ``400kbit``)."""
        done = subprocess.run(["ip", "netns", "exec", self.b, "tc", "qdisc", "add", "dev", "ac-b", "root", "tbf",
                               "rate", rate, "burst", "16kb", "latency", "500ms"], capture_output=True, text=True)
        if done.returncode != 0:
            pytest.skip(f"tc cannot shape the link here: {done.stderr.strip()}")


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)} failed: {done.stderr.strip()}")


@contextmanager
def netns_pair() -> Iterator[NetnsPair]:
    tag = uuid.uuid4().hex[:8]
    pair = NetnsPair(a=f"ac-{tag}-a", b=f"ac-{tag}-b")
    try:
        _ip("netns", "add", pair.a)
        _ip("netns", "add", pair.b)
        _ip("link", "add", "ac-a", "netns", pair.a, "type", "veth", "peer", "name", "ac-b", "netns", pair.b)
        for ns, dev, addr in ((pair.a, "ac-a", ADDR_A), (pair.b, "ac-b", ADDR_B)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        yield pair
    finally:
        for ns in (pair.a, pair.b):  # deleting a namespace deletes its end of the veth pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def with_overrides(path: Path, overrides: dict[str, object], name: str | None = None) -> Path:
    """A copy of a Zenoh JSON5 config with slash-keyed values replaced (same directory, mode 0600)."""
    config = json5.loads(path.read_text())
    for key, value in overrides.items():
        node = config
        *parents, last = key.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    out = path.with_name(name or f"{path.stem}-test.json5")
    out.write_text(json.dumps(config, indent=2))
    out.chmod(0o600)
    return out


def fast_configs(secure: SecureSet) -> dict[str, Path]:
    """The profile's configs with a short link lease, so a cut link is noticed quickly."""
    return {role: with_overrides(path, {"transport/link/tx/lease": LINK_LEASE_MS})
            for role, path in secure.configs.items()}


@pytest.fixture()
def site(tmp_path):
    """Namespaces A and B, a secure profile for a router on A's address, and its router running in A."""
    secure = init_secure(SecureInitConfig(tmp_path / "profile", router_endpoint=f"tls/{ADDR_A}:{PORT}"))
    configs = fast_configs(secure)
    started: list[Proc] = []
    with netns_pair() as pair:
        try:
            started.append(start_router(configs["router"], prefix=pair.exec_prefix(pair.a)))
            yield pair, configs, started
        finally:
            for proc in reversed(started):
                proc.stop()


SERVE = """
import sys, threading, zenoh
session = zenoh.open(zenoh.Config.from_file(sys.argv[1]))
queryable = session.declare_queryable(sys.argv[2], lambda q: q.reply(q.key_expr, b"pong"))
print("serving", flush=True)
threading.Event().wait()
"""

ASK = """
import sys, time, zenoh
session = zenoh.open(zenoh.Config.from_file(sys.argv[1]))
n = 0
while True:
    n += 1
    got = [r.ok.payload.to_bytes() for r in session.get(sys.argv[2], timeout=0.5) if r.ok is not None]
    print(f"ask {n} {'reply' if got == [b'pong'] else 'none'}", flush=True)
    time.sleep(0.2)
"""


def _script(pair: NetnsPair, ns: str, code: str, *args: str) -> Proc:
    return Proc([*pair.exec_prefix(ns), sys.executable, "-c", code, *args])


def _last_ask(proc: Proc) -> tuple[int, str]:
    asks = [line.split() for line in proc.lines if line.startswith("ask ")]
    return (int(asks[-1][1]), asks[-1][2]) if asks else (0, "")


def test_zenoh_across_the_veth_pair_survives_a_cut(site):
    """Fixture check: the secure profile works between the two addresses, stops when the wire
    is cut and recovers when it is back (client sessions reconnect to the router)."""
    pair, configs, started = site
    started.append(_script(pair, pair.a, SERVE, str(configs["orchestrator"]), f"{NS}/orch/lease"))
    started[-1].wait_line("serving")
    asker = _script(pair, pair.b, ASK, str(configs["worker"]), f"{NS}/orch/lease")
    started.append(asker)
    wait_for(lambda: _last_ask(asker)[1] == "reply", 30, "a reply from namespace A at namespace B")
    pair.link(up=False)
    cut_at = _last_ask(asker)[0] + 1  # an ask already in flight may still complete
    wait_for(lambda: _last_ask(asker)[0] > cut_at and _last_ask(asker)[1] == "none", 30,
               "asks to go unanswered while the wire is cut")
    assert stays_false(lambda: _last_ask(asker)[0] > cut_at + 1 and _last_ask(asker)[1] == "reply"), \
        asker.output()
    pair.link(up=True)
    wait_for(lambda: _last_ask(asker)[1] == "reply", 60, "the worker side to reconnect after the cut")


#: A worker process: the real agent, its config checked with validate_secure_config first,
#: and patient: it retries an upload nobody answers until the lease is lost. argv: CONFIG WORKER_ID REALTIME PART_KB
WORKER = """
import logging, sys
from pathlib import Path
from orchestrator.transport import validate_secure_config
from workers.agent import Worker, WorkerConfig
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(name)s %(levelname)s %(message)s")
validate_secure_config(sys.argv[1])
worker = Worker(WorkerConfig(worker_id=sys.argv[2], zenoh_config=Path(sys.argv[1]), realtime=float(sys.argv[3]),
                             max_episodes=1, timeout_s=2.0, idle_poll_s=0.2, max_backoff_s=0.5,
                             part_bytes=int(sys.argv[4]) * 1024))
worker.install_signal_handlers()
print("worker done, uploaded", worker.run(), flush=True)
"""


def start_worker(config: Path, worker_id: str, realtime: float = 0.0, prefix: tuple[str, ...] = (),
                 part_kb: int = DEFAULT_PART_KB) -> Proc:
    return Proc([*prefix, sys.executable, "-c", WORKER, str(config), worker_id, str(realtime), str(part_kb)])


def enqueue(queue: RequestQueue, steps: int = 8, seed: int = 0) -> str:
    state = sample_state(np.random.default_rng(seed), shape="box")
    request, _ = queue.enqueue(NewRequest(task="push", shape="box", start_state=state.to_dict(),
                                          policy="push", steps=steps))
    return request.id


#: The orchestrator service, run in namespace A. argv: CONFIG DATA_DIR LEASE_S
SERVICE = """
import logging, signal, sys, threading
from pathlib import Path
from orchestrator.transport import validate_secure_config
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(name)s %(levelname)s %(message)s")
validate_secure_config(sys.argv[1])
service = Service(ServiceConfig(data_dir=Path(sys.argv[2]), zenoh_config=Path(sys.argv[1]),
                                lease_s=float(sys.argv[3]), reap_interval_s=0.2))
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
service.start()
print("serving", flush=True)
while not stop.wait(0.5):
    pass
service.stop()
"""


@pytest.fixture()
def deployment(site, tmp_path):
    """``site`` plus the orchestrator service in namespace A; yields (pair, configs, started, queue, data)."""
    pair, configs, started = site
    data = tmp_path / "data"
    service = _script(pair, pair.a, SERVICE, str(configs["orchestrator"]), str(data), "3.0")
    started.append(service)
    service.wait_line("serving")
    queue = RequestQueue(data / "catalog.sqlite")
    try:
        yield pair, configs, started, queue, data
    finally:
        queue.close()


def _stored(data: Path, request_id: str) -> list[str]:
    catalog = Catalog(data)
    return [row.episode_id for row in catalog.list() if row.request_id == request_id]


def test_loop_works_across_the_two_addresses(deployment):
    pair, configs, started, queue, data = deployment
    request_id = enqueue(queue)
    worker = start_worker(configs["worker"], "far-w1", prefix=pair.exec_prefix(pair.b))
    started.append(worker)
    wait_for(lambda: queue.get(request_id).status == RequestStatus.DONE, 90,
               f"the request to be done by the worker at {ADDR_B}")
    assert worker.popen.wait(60) == 0, worker.output()
    done = queue.get(request_id)
    assert done.worker_id == "far-w1" and _stored(data, request_id) == [done.episode_id]


def test_cut_mid_episode_is_released_redone_and_the_late_upload_refused(deployment):
    """Cut B's wire while its worker holds the lease: the service gives the request back (the
    worker's liveliness goes with the link, and its 3 s lease runs out), a worker in A completes
    it, and once the wire is back the cut worker's upload carries a stale fencing token."""
    pair, configs, started, queue, data = deployment
    request_id = enqueue(queue, steps=30)
    # the cut worker paces its 30 steps at half a robot's speed (6 s): the wire is cut mid-episode
    cut = start_worker(configs["worker"], "cut-w1", realtime=2.0, prefix=pair.exec_prefix(pair.b))
    started.append(cut)
    wait_for(lambda: queue.get(request_id).status == RequestStatus.LEASED, 90, "the first lease")
    wait_for(lambda: holds("\n".join(cut.lines), request_id), 30, "the cut worker to hold it")  # (its grant too)
    first = queue.get(request_id)
    assert first.worker_id == "cut-w1"
    pair.link(up=False)
    other = start_worker(configs["worker"], "near-w2", prefix=pair.exec_prefix(pair.a))
    started.append(other)
    wait_for(lambda: queue.get(request_id).status == RequestStatus.DONE, 90,
               "the request to be leased again and completed by the other worker")
    done = queue.get(request_id)
    assert done.worker_id == "near-w2" and done.token > first.token
    assert other.popen.wait(60) == 0, other.output()
    # the cut worker finished its episode and keeps trying to upload it while cut off
    cut.wait_line("upload: ", timeout=60)
    pair.link(up=True)
    cut.wait_line(f"upload of {request_id} refused (stale_token", timeout=90)
    assert f"uploaded {request_id}" not in cut.output(), cut.output()
    assert _stored(data, request_id) == [done.episode_id]
    assert len(list((data / "episodes").rglob("*.mcap"))) == 1
    assert queue.get(request_id).episode_id == done.episode_id


def test_an_episode_longer_to_send_than_a_lease_keeps_its_lease_over_a_slow_uplink(deployment):
    """B's uplink at 50 kB/s: a 1000-step episode (~660 kB) takes 13 s to send, four of the service's 3 s leases.
    Sent whole, as one message, it held the link: the renewals waited behind its bytes, the lease expired and the
    episode was dropped (and its 2 s reply wait ran out on every try). Sent in parts of 32 kB, each answered
    before the next goes, renewals get through between the parts: stored under the first lease. (The worker's
    Zenoh shares no memory with the router's here, as on another host: on this one it would pass big payloads
    through /dev/shm, around the veth pair.)"""
    pair, configs, started, queue, data = deployment
    pair.throttle("400kbit")
    request_id = enqueue(queue, steps=1000)
    remote = with_overrides(configs["worker"], {"transport/shared_memory/enabled": False}, "worker-remote.json5")
    worker = start_worker(remote, "slow-w1", prefix=pair.exec_prefix(pair.b), part_kb=32)
    started.append(worker)
    assert worker.popen.wait(180) == 0, worker.output()
    done = queue.get(request_id)
    assert (done.status, done.worker_id, done.token, done.attempts) == (RequestStatus.DONE, "slow-w1", 1, 0), \
        worker.output()
    assert _stored(data, request_id) == [done.episode_id]
    assert Catalog(data).get(done.episode_id).size_bytes > 10 * 32 * 1024  # (it did take many parts)
