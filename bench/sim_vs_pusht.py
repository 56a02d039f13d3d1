"""Our collector against gym-pusht, side by side in one run, at 96x96 pixels.

gym-pusht (the PushT environment of LeRobot) needs pymunk 6, so it lives in its
own virtual environment, ``bench/.venv-pusht`` (created here on first use with
``pip install gym-pusht``), and is stepped there in a subprocess: pixel
observations 96x96, random actions, resets at episode ends. Ours runs in this
process: ``workers.simbench.run_sim_bench`` (simulate + render + encode MCAP +
atomic write to disk, fsync included), with gym-pusht's episode length so that
both sides reset equally often.

Each round runs the two at the same time for the same wall-clock window, so
load from other users of the machine hits both alike (``--mode alternate`` runs
them one after the other instead). Figures per round: wall-clock rates and
their ratio (the headline), ``ratio_without_disk`` (our rate leaving out the
file write: a worker uploads its bytes instead), and ``ratio_cpu`` (steps per
CPU-second of each process). The JSON printed at the end has every round and
the medians.

Usage: .venv/bin/python bench/sim_vs_pusht.py [--seconds 5] [--rounds 3] [--size 96]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import venv
from pathlib import Path

from workers.simbench import run_sim_bench
from storage.records import MAX_FRAME_SIZE, MIN_FRAME_SIZE

HERE = Path(__file__).resolve().parent
PUSHT_VENV = HERE / ".venv-pusht"
PUSHT_PYTHON = PUSHT_VENV / "bin" / "python"

# Builds the env, says "ready", waits for a line on stdin, then steps for `seconds`.
PUSHT_LOOP = """
import json, sys, time
import gymnasium as gym
import gym_pusht  # noqa: F401  (registers gym_pusht/PushT-v0)
import pymunk
size, seconds = int(sys.argv[1]), float(sys.argv[2])
env = gym.make("gym_pusht/PushT-v0", obs_type="pixels", render_mode="rgb_array",
               observation_width=size, observation_height=size)
obs, _ = env.reset(seed=0)
env.action_space.seed(0)
assert obs.shape == (size, size, 3), obs.shape
print("ready", flush=True)
sys.stdin.readline()
steps = 0
cpu0, start = time.process_time(), time.perf_counter()
while time.perf_counter() - start < seconds:
    obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
    steps += 1
    if terminated or truncated:
        env.reset()
elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu0
print(json.dumps({"steps": steps, "seconds": elapsed, "steps_per_s": steps / elapsed,
                  "steps_per_cpu_s": steps / cpu, "pymunk": pymunk.version,
                  "episode_steps": env.spec.max_episode_steps}), flush=True)
"""


def ensure_pusht_venv() -> None:
    """Creates bench/.venv-pusht with gym-pusht unless gym-pusht already imports there."""
    if PUSHT_PYTHON.exists() and subprocess.run([str(PUSHT_PYTHON), "-c", "import gym_pusht"],
                                                capture_output=True).returncode == 0:
        return
    print(f"creating {PUSHT_VENV} and installing gym-pusht (once)", file=sys.stderr)
    if not PUSHT_PYTHON.exists():
        venv.create(PUSHT_VENV, with_pip=True)
    subprocess.run([str(PUSHT_PYTHON), "-m", "pip", "install", "-q", "gym-pusht"], check=True)


class PushT:
    """gym-pusht's stepping loop in its venv, started and made ready before the clock runs."""

    def __init__(self, size: int, seconds: float) -> None:
        self.proc = subprocess.Popen([str(PUSHT_PYTHON), "-c", PUSHT_LOOP, str(size), str(seconds)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline().strip()
        if line != "ready":
            self.proc.kill()
            raise RuntimeError(f"gym-pusht loop did not start (said {line!r}, exit {self.proc.wait()})")

    def go(self) -> None:
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()

    def result(self) -> dict:
        out, _ = self.proc.communicate()
        if self.proc.returncode != 0:
            raise RuntimeError(f"gym-pusht loop failed with exit {self.proc.returncode}")
        return json.loads(out.strip().splitlines()[-1])


# gym-pusht's PushT-v0 resets every 300 steps; read from the env in the first round.
PUSHT_EPISODE_STEPS = 300


def one_round(i: int, size: int, seconds: float, mode: str) -> dict:
    pusht = PushT(size, seconds)
    if mode == "concurrent":
        pusht.go()
        ours = run_sim_bench(image_size=size, seconds=seconds, steps_per_episode=PUSHT_EPISODE_STEPS)
        theirs = pusht.result()
    else:
        pusht.go()
        theirs = pusht.result()
        ours = run_sim_bench(image_size=size, seconds=seconds, steps_per_episode=PUSHT_EPISODE_STEPS)
    if theirs["episode_steps"] != PUSHT_EPISODE_STEPS:
        raise RuntimeError(f"gym-pusht episodes are {theirs['episode_steps']} steps, expected {PUSHT_EPISODE_STEPS}")
    without_disk = ours["frames"] / (ours["simulate_render_s"] + ours["encode_s"])
    return {
        "round": i, "mode": mode,
        "pusht_steps_per_s": theirs["steps_per_s"], "ours_frames_per_s": ours["frames_per_s"],
        "ratio": ours["frames_per_s"] / theirs["steps_per_s"],
        "ratio_without_disk": without_disk / theirs["steps_per_s"],
        "pusht_steps_per_cpu_s": theirs["steps_per_cpu_s"], "ours_frames_per_cpu_s": ours["frames_per_cpu_s"],
        "ratio_cpu": ours["frames_per_cpu_s"] / theirs["steps_per_cpu_s"],
        "ours_simulate_render_s": ours["simulate_render_s"], "ours_encode_s": ours["encode_s"],
        "ours_write_s": ours["write_s"], "ours_seconds": ours["seconds"], "pusht_seconds": theirs["seconds"],
        "episode_steps": PUSHT_EPISODE_STEPS, "pusht_pymunk": theirs["pymunk"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="duration of each measurement")
    parser.add_argument("--rounds", type=int, default=3, help="rounds; medians are reported")
    parser.add_argument("--size", type=int, default=96, help="frame side in pixels")
    parser.add_argument("--mode", choices=("concurrent", "alternate"), default="concurrent",
                        help="run the two at the same time (default) or one after the other")
    args = parser.parse_args(argv)
    # before the venv is made (a download) and before either side starts: one line, exit 2
    if args.rounds < 1 or not 0 < args.seconds < float("inf") or not MIN_FRAME_SIZE <= args.size <= MAX_FRAME_SIZE:
        parser.error(f"--rounds must be at least 1, --seconds positive and --size in [{MIN_FRAME_SIZE}, "
                     f"{MAX_FRAME_SIZE}]; found {args.rounds}, {args.seconds}, {args.size}")
    ensure_pusht_venv()
    rounds = []
    for i in range(args.rounds):
        rounds.append(one_round(i, args.size, args.seconds, args.mode))
        print(json.dumps(rounds[-1]), file=sys.stderr)

    def median(key: str) -> float:
        return statistics.median(r[key] for r in rounds)

    result = {
        "bench": "sim_vs_pusht", "image_size": args.size, "seconds_per_measurement": args.seconds,
        "mode": args.mode, "rounds_run": args.rounds,
        "pusht_steps_per_s_median": median("pusht_steps_per_s"),
        "ours_frames_per_s_median": median("ours_frames_per_s"),
        "ratio_median": median("ratio"), "ratio_without_disk_median": median("ratio_without_disk"),
        "ratio_cpu_median": median("ratio_cpu"), "rounds": rounds,
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
