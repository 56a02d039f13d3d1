"""What one oversized message costs a receiving process, with Zenoh's cap on incoming messages and without.

``transport.make_config`` caps one reassembled incoming message at ``RX_MAX_MESSAGE_BYTES`` (65 MiB);
Zenoh's own default is 1 GiB. This starts two receivers as subprocesses on loopback, each serving a
queryable as the service does: one with our config, one with the cap put back to Zenoh's default.
A peer (this process, shared memory off: the path a worker on another host takes) sends each a query
of --mb MiB, waits for its reply or its timeout, then sends a small query. Each receiver reports the
peak resident memory it reached (``VmHWM``) before and after, whether its handler saw the big
message, and whether it answered the small one. Both receivers run in the same invocation, so the
ratio compares like with like.

Usage: .venv/bin/python bench/zenoh_cap.py [--mb 300] [--timeout 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

RECEIVER = """
import json, sys
from orchestrator import transport
def peak_kib():  # VmHWM: this process's own peak (ru_maxrss would carry the parent's across fork and exec)
    return int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])
endpoint, key, uncapped = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
config = transport.make_config(listen=[endpoint])
if uncapped:
    config.insert_json5(transport.RX_MAX_MESSAGE_SIZE_KEY, str(1 << 30))  # Zenoh's default
import zenoh
session = zenoh.open(config)
seen = []
def answer(query):
    size = len(query.payload.to_bytes()) if query.payload is not None else 0
    seen.append(size)
    query.reply(key, str(size))
try:  # an open session's threads would keep this process alive: close it however we leave
    queryable = session.declare_queryable(key, answer)
    print(json.dumps({"ready": True, "maxrss_kib": peak_kib()}), flush=True)
    sys.stdin.readline()  # the sender is done (or gone: end of file)
    print(json.dumps({"seen_bytes": seen, "maxrss_kib": peak_kib()}), flush=True)
    queryable.undeclare()
except BrokenPipeError:  # the sender went away
    pass
finally:
    session.close()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ask(session, key: str, payload: bytes, timeout: float) -> str:
    replies = list(session.get(key, payload=payload, timeout=timeout))
    ok = [r.ok for r in replies if r.ok is not None]
    return ok[0].payload.to_string() if ok else "no reply (timed out)"


def measure(mb: int, timeout: float, uncapped: bool) -> dict:
    import zenoh
    from orchestrator import transport
    endpoint, key = f"tcp/127.0.0.1:{_free_port()}", "bench/zenoh_cap"
    # Its own process group: a terminal's Ctrl-C is ours to handle; the receiver stops when its stdin closes.
    proc = subprocess.Popen([sys.executable, "-c", RECEIVER, endpoint, key, "1" if uncapped else "0"],
                            cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, process_group=0)
    try:
        before = json.loads(proc.stdout.readline())
        config = transport.make_config(connect=[endpoint])
        config.insert_json5("transport/shared_memory/enabled", "false")
        session = zenoh.open(config)
        try:
            deadline = time.monotonic() + 10
            while _ask(session, key, b"hello", 1.0).startswith("no reply") and time.monotonic() < deadline:
                pass  # until the link is up
            t0 = time.perf_counter()
            big = _ask(session, key, bytes(mb << 20), timeout)
            big_s = time.perf_counter() - t0
            small = _ask(session, key, b"still there?", 5.0)
        finally:
            session.close()
        proc.stdin.write("done\n")
        proc.stdin.flush()
        after = json.loads(proc.stdout.readline())
    finally:
        proc.stdin.close()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
    return {"cap_bytes": (1 << 30) if uncapped else transport.RX_MAX_MESSAGE_BYTES,
            "big_reply": big, "big_seconds": round(big_s, 2), "small_reply": small,
            "handler_saw_big": any(n >= mb << 20 for n in after["seen_bytes"]),
            "receiver_peak_mib_before": round(before["maxrss_kib"] / 1024, 1),
            "receiver_peak_mib_after": round(after["maxrss_kib"] / 1024, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mb", type=int, default=300, help="size of the oversized query in MiB (default 300)")
    parser.add_argument("--timeout", type=float, default=20.0, help="how long the sender waits for its reply")
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args(argv)
    if args.mb < 1 or not args.timeout > 0:
        parser.error("--mb must be >= 1 and --timeout > 0")
    capped, uncapped = measure(args.mb, args.timeout, False), measure(args.mb, args.timeout, True)
    grew = [r["receiver_peak_mib_after"] - r["receiver_peak_mib_before"] for r in (capped, uncapped)]
    out = {"mb": args.mb, "capped": capped, "zenoh_default": uncapped,
           "growth_ratio_default_over_capped": round(grew[1] / grew[0], 2) if grew[0] > 0 else None,
           "sender_maxrss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
