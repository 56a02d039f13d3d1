"""The collector's speed: recorded frames per second for one process.

A recorded frame is one control step simulated (10 physics substeps), rendered,
its state read, and the episode it belongs to encoded as MCAP and written to
disk atomically (``storage.episodes.write_episode``: temp file, fsync, rename).
This is what ``activecollect bench sim`` prints and what ``bench/sim_vs_pusht.py``
compares with gym-pusht.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from orchestrator.protocol import SHAPES
from storage.episodes import encode_episode
from storage.files import write_bytes_atomic
from workers.collect import collect_episode
from workers.env import sample_state


def run_sim_bench(image_size: int = 96, seconds: float = 5.0, out_dir: str | Path | None = None,
                  steps_per_episode: int = 100, policy: str = "push", seed: int = 0) -> dict:
    """Collects and writes episodes for about ``seconds``; returns the figures as a dict.

    Keys: frames_per_s (the headline), frames, episodes, seconds (measured), image_size,
    steps_per_episode, policy, bytes_per_frame, the split of the time between
    simulate_render_s, encode_s and write_s, and cpu_s / frames_per_cpu_s (this process's
    CPU time, which other users of a shared machine disturb less than wall time). ``out_dir`` keeps the files
    (a temporary directory, removed afterwards, when None). Raises ValueError for a bad argument.
    """
    if not seconds > 0:
        raise ValueError(f"seconds: expected > 0, found {seconds}")
    if out_dir is None:
        with tempfile.TemporaryDirectory(prefix="activecollect-simbench-") as tmp:
            return _run(image_size, seconds, Path(tmp), steps_per_episode, policy, seed)
    return _run(image_size, seconds, Path(out_dir), steps_per_episode, policy, seed)


def _run(image_size: int, seconds: float, out_dir: Path, steps: int, policy: str, seed: int) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frames = episodes = size = 0
    sim_s = encode_s = write_s = 0.0
    cpu_start = time.process_time()
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        t0 = time.perf_counter()
        state = sample_state(rng, shape=SHAPES[episodes % len(SHAPES)])
        ep = collect_episode(start_state=state, policy=policy, seed=int(rng.integers(2**31)),
                             steps=steps, image_size=image_size)
        t1 = time.perf_counter()
        data = encode_episode(ep)
        t2 = time.perf_counter()
        write_bytes_atomic(out_dir / f"{ep.meta.episode_id}.mcap", data)
        t3 = time.perf_counter()
        sim_s, encode_s, write_s = sim_s + (t1 - t0), encode_s + (t2 - t1), write_s + (t3 - t2)
        frames += len(ep)
        episodes += 1
        size += len(data)
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    return {
        "bench": "sim", "frames_per_s": frames / elapsed, "frames": frames, "episodes": episodes,
        "seconds": elapsed, "image_size": image_size, "steps_per_episode": steps, "policy": policy,
        "bytes_per_frame": size / max(frames, 1), "simulate_render_s": sim_s, "encode_s": encode_s,
        "write_s": write_s, "cpu_s": cpu, "frames_per_cpu_s": frames / cpu if cpu > 0 else 0.0,
    }
