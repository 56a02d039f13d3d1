"""``HeapTrimmer``: freed heap memory a process keeps goes back to the system, at most every interval."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.heap import HeapTrimmer

ROOT = Path(__file__).resolve().parents[2]

FRAGMENTED = """
import ctypes, json
from orchestrator.heap import HeapTrimmer
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def rss_mib():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
base, big, small = rss_mib(), [], []
for _ in range(1000):  # 100 kB blocks (under the mmap threshold: from the heap), each pinned by a small one after it
    block = libc.malloc(100_000)
    ctypes.memset(block, 1, 100_000)
    big.append(block)
    small.append(libc.malloc(64))
for block in big:
    libc.free(block)
freed = rss_mib()
trimmer = HeapTrimmer()
print(json.dumps({"available": trimmer.available, "base": base, "freed": freed, "trimmed": trimmer(),
                  "after": rss_mib()}))
"""


def test_free_heap_memory_the_process_kept_goes_back_to_the_system():
    proc = subprocess.run([sys.executable, "-c", FRAGMENTED], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    seen = json.loads(proc.stdout)
    if not seen["available"]:
        pytest.skip("this C library has no malloc_trim")
    assert seen["freed"] > seen["base"] + 80, seen  # ~100 MB freed, kept by the process
    assert seen["trimmed"] and seen["after"] < seen["base"] + 20, seen


def test_it_trims_at_most_once_an_interval():
    now = [100.0]
    trimmer = HeapTrimmer(interval_s=5.0, clock=lambda: now[0])
    if not trimmer.available:
        pytest.skip("this C library has no malloc_trim")
    assert trimmer() and not trimmer() and trimmer.trims == 1
    now[0] += 4.9
    assert not trimmer()
    now[0] += 0.1
    assert trimmer() and trimmer.trims == 2
    with pytest.raises(ValueError, match="interval_s must be >= 0, found -1"):
        HeapTrimmer(interval_s=-1)
