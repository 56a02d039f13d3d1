"""Uploads whole or in parts (``orchestrator.upload_parts``): what parts cost on a fast link, what they save on a
slow one.

Two network namespaces joined by a veth pair (needs root, ``ip`` and ``tc``): the service (``Service``, a plain
peer on ``tcp/10.232.0.1:7447``) runs in A, a client in B that does what a worker does with a lease: it renews it
every lease_s / 3 on a thread of its own and uploads an episode of --steps steps at 64 px, sent whole or in parts
of --part-kb (``workers.upload.EpisodeUpload``, the worker's own code), alternating, --rounds times each. With
--rate (tc's words, e.g. ``400kbit``) B's uplink is shaped to it; without, the link is the veth's own speed. The
client's Zenoh shares no memory with the service's (as on another host; on one host Zenoh would pass big payloads
through /dev/shm, around the link).

Reported per mode: the upload's time to its reply (median), the longest a renewal waited for its reply while the
upload was out (median over rounds), and the rounds whose lease was lost (a renewal refused, or the upload refused
as stale) or whose upload was never acknowledged within --timeout; and parts ÷ whole of the median upload time
(when every upload of both was stored: else one is a time to fail).

Usage: sudo .venv/bin/python bench/upload_parts.py [--rate 400kbit] [--rounds 3] [--steps 1000] [--part-kb 32]
       [--lease-s 3] [--timeout 30] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ADDR_A, ADDR_B, PORT = "10.232.0.1", "10.232.0.2", 7447

SERVICE = """
import signal, sys, threading
from pathlib import Path
from orchestrator.service import Service
from orchestrator.serviceconfig import ServiceConfig
service = Service(ServiceConfig(data_dir=Path(sys.argv[1]), listen=(sys.argv[2],), lease_s=float(sys.argv[3]),
                                reap_interval_s=0.2))
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
service.start()
print("serving", flush=True)
stop.wait()
service.stop()
"""

CLIENT = """
import json, sys, threading, time
import numpy as np
from orchestrator import messages, protocol, transport
from orchestrator.protocol import Keys, ProtocolError
from storage.episodes import encode_episode
from workers.collect import collect_episode
from workers.upload import EpisodeUpload
endpoint, rounds, part_kb, timeout = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
config = transport.make_config(connect=[endpoint])
config.insert_json5("transport/shared_memory/enabled", "false")
import zenoh
session, keys = zenoh.open(config), Keys("activecollect")

def call(key, payload, attachment=None, wait=timeout):
    return protocol.parse_reply(transport.query(session, key, payload, attachment, timeout=wait))

def one(mode):
    grant = messages.LeaseGrant.from_dict(call(keys.lease, messages.LeaseRequest(worker_id="b1").to_json())["grant"])
    episode = collect_episode(start_state=grant.start_state, policy=grant.policy, policy_params=grant.policy_params,
                              seed=grant.seed, steps=grant.steps, image_size=64, request_id=grant.request_id,
                              worker_id="b1")
    data = encode_episode(episode)
    renew = messages.RenewRequest(request_id=grant.request_id, token=grant.token, worker_id="b1").to_json()
    waits, lost, out, stop = [], [], threading.Event(), threading.Event()
    def renewer():
        while not stop.wait(grant.lease_s / 3):
            sent = time.monotonic()
            try:
                call(keys.renew, renew, wait=grant.lease_s)
            except ProtocolError as exc:
                lost.append(exc.code.value)
                return
            except transport.TransportError:
                pass
            if out.is_set():
                waits.append(time.monotonic() - sent)
    thread = threading.Thread(target=renewer, daemon=True)
    thread.start()
    upload = EpisodeUpload(data, grant.request_id, grant.token, "b1", part_kb * 1024 if mode == "parts" else len(data))
    out.set()
    start, result = time.monotonic(), "stored"
    try:
        upload.send_with(lambda payload, attachment: call(keys.upload, payload, attachment))
    except ProtocolError as exc:
        result = exc.code.value
    except transport.TransportError:
        result = "no reply"
    took = time.monotonic() - start
    out.clear()
    stop.set()
    thread.join()
    if result != "stored":  # give the request back so the next round has one
        try:
            call(keys.release, messages.ReleaseRequest(request_id=grant.request_id, token=grant.token,
                                                       worker_id="b1").to_json())
        except (ProtocolError, transport.TransportError):
            pass
    return {"mode": mode, "bytes": len(data), "upload_s": round(took, 3), "result": result,
            "longest_renewal_wait_s": round(max(waits), 3) if waits else None, "lease_lost": bool(lost)}

for _ in range(rounds):
    for mode in ("whole", "parts"):
        print(json.dumps(one(mode)), flush=True)
"""


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", default=None, help="shape B's uplink to this (tc's words: 400kbit); default: none")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--part-kb", type=int, default=32)
    parser.add_argument("--lease-s", type=float, default=3.0)
    parser.add_argument("--timeout", type=float, default=30.0, help="the client's wait for each reply (s)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None:
        parser.exit(2, "upload_parts: error: needs root, ip and tc (network namespaces and a shaped veth pair)\n")
    sys.path.insert(0, str(REPO))
    from storage.queue import RequestQueue  # noqa: E402 -- after the root check: torch-free but not instant
    from storage.requests import NewRequest
    from workers.env import sample_state
    import numpy as np

    tag = uuid.uuid4().hex[:6]
    a, b = f"acb-{tag}-a", f"acb-{tag}-b"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="upload-parts-") as tmp:
        try:
            _ip("netns", "add", a)
            _ip("netns", "add", b)
            _ip("link", "add", "acb-a", "netns", a, "type", "veth", "peer", "name", "acb-b", "netns", b)
            for ns, dev, addr in ((a, "acb-a", ADDR_A), (b, "acb-b", ADDR_B)):
                _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
                _ip("-n", ns, "link", "set", dev, "up")
                _ip("-n", ns, "link", "set", "lo", "up")
            if args.rate:
                subprocess.run(["ip", "netns", "exec", b, "tc", "qdisc", "add", "dev", "acb-b", "root", "tbf", "rate",
                                args.rate, "burst", "16kb", "latency", "500ms"], check=True)
            data = Path(tmp) / "data"
            data.mkdir()
            queue = RequestQueue(data / "catalog.sqlite")
            rng = np.random.default_rng(0)
            for _ in range(2 * args.rounds):
                queue.enqueue(NewRequest(task="push", shape="box", policy="push", steps=args.steps,
                                         start_state=sample_state(rng, shape="box").to_dict()))
            queue.close()
            service = subprocess.Popen(["ip", "netns", "exec", a, sys.executable, "-c", SERVICE, str(data),
                                        f"tcp/{ADDR_A}:{PORT}", str(args.lease_s)], stdout=subprocess.PIPE,
                                       stderr=subprocess.DEVNULL, text=True, env=env)
            procs.append(service)
            if service.stdout.readline().strip() != "serving":
                parser.exit(1, "upload_parts: the service did not start\n")
            client = subprocess.run(["ip", "netns", "exec", b, sys.executable, "-c", CLIENT, f"tcp/{ADDR_A}:{PORT}",
                                     str(args.rounds), str(args.part_kb), str(args.timeout)],
                                    capture_output=True, text=True, env=env)
            if client.returncode != 0:
                parser.exit(1, f"upload_parts: the client failed:\n{client.stderr[-3000:]}\n")
        finally:
            for proc in procs:
                proc.terminate()
                proc.wait(30)
            for ns in (a, b):
                subprocess.run(["ip", "netns", "del", ns], capture_output=True)
    rounds = [json.loads(line) for line in client.stdout.splitlines() if line.startswith("{")]
    summary: dict = {"rate": args.rate or "unshaped", "steps": args.steps, "part_kb": args.part_kb,
                     "lease_s": args.lease_s, "timeout_s": args.timeout, "rounds": rounds, "modes": {}}
    for mode in ("whole", "parts"):
        mine = [r for r in rounds if r["mode"] == mode]
        waits = [r["longest_renewal_wait_s"] for r in mine if r["longest_renewal_wait_s"] is not None]
        summary["modes"][mode] = {
            "median_upload_s": statistics.median(r["upload_s"] for r in mine),
            "median_longest_renewal_wait_s": statistics.median(waits) if waits else None,
            "leases_lost": sum(r["lease_lost"] or r["result"] == "stale_token" for r in mine),
            "not_stored": sum(r["result"] != "stored" for r in mine), "rounds": len(mine)}
    whole, parts = summary["modes"]["whole"], summary["modes"]["parts"]
    both_stored = not whole["not_stored"] and not parts["not_stored"]  # (else a time is a time to fail)
    summary["parts_over_whole_upload_s"] = (round(parts["median_upload_s"] / whole["median_upload_s"], 3)
                                            if both_stored else None)
    print(json.dumps(summary["modes"], indent=2))
    print(f"parts / whole, median upload time: {summary['parts_over_whole_upload_s']}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
