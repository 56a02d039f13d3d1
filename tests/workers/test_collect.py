"""Collecting episodes: layout, provenance, prefix replay, MCAP round trip, eval split, sim bench."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import uuid

import numpy as np
import pytest

from storage.catalog import Catalog
from storage.episode_reader import read_episode
from storage.episodes import encode_episode
from storage.records import STATE_DIM
from workers.collect import EvalSplitConflict, collect_episode, create_eval_split
from workers.env import PHYSICS_RANGES, SHAPE_PALETTE, PushSim, SimState, sample_state
from workers.simbench import run_sim_bench


@pytest.fixture
def start() -> SimState:
    return sample_state(np.random.default_rng(5), shape="T")


def test_episode_layout_and_provenance(start):
    ep = collect_episode(start_state=start, policy="push", policy_params={"side": "left"}, seed=3,
                         steps=12, image_size=24, request_id="r1", worker_id="w1", model_version="m3")
    assert ep.frames.shape == (12, 24, 24, 3) and ep.frames.dtype == np.uint8
    assert ep.actions.shape == (12, 2) and ep.actions.dtype == np.float32
    assert ep.states.shape == (12, STATE_DIM) and ep.states.dtype == np.float64
    np.testing.assert_array_equal(ep.states[0, :10], start.to_vector()[:10])
    m = ep.meta
    assert uuid.UUID(hex=m.episode_id).version == 4
    assert (m.task, m.shape, m.policy, m.seed) == ("push", "T", "push", 3)
    assert m.policy_params["side"] == "left" and m.physics == start.physics
    assert SimState.from_dict(m.start_state) == start
    assert (m.request_id, m.worker_id, m.model_version) == ("r1", "w1", "m3")
    assert m.action_prefix_len == 0 and m.image_size == 24 and m.control_hz == 10.0
    assert m.software_version and m.created.endswith("+00:00")


def test_frames_and_states_follow_the_actions(start):
    """frames[t], states[t] are observed before actions[t]: replaying in a bare sim gives the same."""
    ep = collect_episode(start_state=start, policy="random_waypoints", seed=8, steps=15, image_size=16)
    sim = PushSim(16)
    sim.reset(start)
    for t in range(len(ep)):
        assert np.array_equal(sim.render(), ep.frames[t])
        assert np.array_equal(sim.state_vector(), ep.states[t])
        sim.step(float(ep.actions[t, 0]), float(ep.actions[t, 1]))


def test_same_seed_same_episode(start):
    a = collect_episode(start_state=start, policy="push", seed=4, steps=20, image_size=16)
    b = collect_episode(start_state=start.to_dict(), policy="push", seed=4, steps=20, image_size=16)
    assert a.frames.tobytes() == b.frames.tobytes() and a.actions.tobytes() == b.actions.tobytes()
    assert a.meta.episode_id != b.meta.episode_id


def test_action_prefix_replay_reaches_the_original_state(start):
    original = collect_episode(start_state=start, policy="push", seed=1, steps=30, image_size=16)
    k = 17
    again = collect_episode(start_state=original.meta.start_state, policy="random_waypoints", seed=99,
                            steps=10, image_size=16, action_prefix=original.actions[:k].tolist())
    assert len(again) == k + 10 and again.meta.action_prefix_len == k
    np.testing.assert_array_equal(again.actions[:k], original.actions[:k])
    # The state the prefix leads to (and every frame before it) is the original's, bit for bit.
    np.testing.assert_array_equal(again.states[:k + 1], original.states[:k + 1])
    assert again.frames[:k + 1].tobytes() == original.frames[:k + 1].tobytes()
    assert not np.array_equal(again.actions[k:k + 10], original.actions[k:k + 10])


def test_mcap_round_trip(start):
    ep = collect_episode(start_state=start, policy="push", seed=2, steps=8, image_size=16)
    back = read_episode(encode_episode(ep))
    assert back.meta == ep.meta
    np.testing.assert_array_equal(back.frames, ep.frames)
    np.testing.assert_array_equal(back.actions, ep.actions)
    np.testing.assert_array_equal(back.states, ep.states)


@pytest.mark.parametrize("kwargs, match", [
    ({"steps": 0}, "steps"),
    ({"steps": 10**6}, "steps"),
    ({"seed": -1}, "seed"),
    ({"policy": "dance"}, "policy"),
    ({"policy_params": {"side": "diagonal"}}, "side"),
    ({"image_size": 4}, "image_size"),
    ({"action_prefix": [[1.0, 2.0, 3.0]]}, "action_prefix"),
    ({"action_prefix": [[1.0, 900.0]]}, "action_prefix"),
    ({"action_prefix": [[1.0, 2.0], [3.0]]}, "action_prefix"),
    ({"start_state": {"shape": "T", "agent": [1, 1]}}, "object"),
])
def test_bad_requests_are_refused(start, kwargs, match):
    args = {"start_state": start, "policy": "push", "seed": 0, "steps": 5, "image_size": 16, **kwargs}
    with pytest.raises(ValueError, match=match):
        collect_episode(**args)


def test_eval_split_is_pinned_idempotent_and_guarded(tmp_path):
    catalog = Catalog(tmp_path / "data")
    digest = create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16)
    split = catalog.eval_split()
    assert split is not None and split.hash == digest and len(split.ids) == 4
    assert catalog.count(split="eval") == 4 and catalog.count(split="train") == 0
    shapes = sorted(catalog.get(i).shape for i in split.ids)
    assert shapes == sorted(["T", "box", "L", "disk"])
    assert all(catalog.get(i).frames == 6 for i in split.ids)
    assert create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16) == digest
    assert catalog.count(split="eval") == 4
    with pytest.raises(EvalSplitConflict, match="already pinned"):
        create_eval_split(catalog, episodes=4, seed=8, steps=6, image_size=16)
    with pytest.raises(EvalSplitConflict, match="palette"):  # a recoloured world is another split
        create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16, palette=SHAPE_PALETTE)


def test_sim_bench_writes_episodes_and_reports_figures(tmp_path):
    out = run_sim_bench(image_size=16, seconds=0.05, out_dir=tmp_path, steps_per_episode=5)
    assert out["frames"] >= 5 and out["episodes"] >= 1 and out["frames_per_s"] > 0
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == out["episodes"]
    assert len(read_episode(files[0])) == 5


def test_episodes_are_identical_across_processes(start):
    """Same seed and start state in a fresh interpreter: the same frame bytes."""
    code = ("import hashlib, json, sys\n"
            "from workers.collect import collect_episode\n"
            "ep = collect_episode(start_state=json.loads(sys.argv[1]), policy='push', seed=6, steps=15,"
            " image_size=32)\n"
            "print(hashlib.sha256(ep.frames.tobytes() + ep.states.tobytes()).hexdigest())\n")
    out = subprocess.run([sys.executable, "-c", code, json.dumps(start.to_dict())], check=True,
                         capture_output=True, text=True, timeout=120)
    ep = collect_episode(start_state=start, policy="push", seed=6, steps=15, image_size=32)
    assert out.stdout.strip() == hashlib.sha256(ep.frames.tobytes() + ep.states.tobytes()).hexdigest()


def test_eval_split_with_random_physics_draws_each_episodes_physics_and_is_another_split(tmp_path):
    catalog = Catalog(tmp_path / "data")
    digest = create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16, random_physics=True)
    split = catalog.eval_split()
    assert split.params["random_physics"] is True
    physics = [catalog.meta(i).physics for i in split.ids]
    assert len({tuple(sorted(p.items())) for p in physics}) == 4
    assert all(low <= p[k] <= high for p in physics for k, (low, high, _) in PHYSICS_RANGES.items())
    assert create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16, random_physics=True) == digest
    with pytest.raises(EvalSplitConflict, match="random_physics"):
        create_eval_split(catalog, episodes=4, seed=7, steps=6, image_size=16)


def test_an_interrupted_eval_split_is_taken_up_again_not_recorded_twice(tmp_path, monkeypatch, capsys):
    """Its episodes are indexed one by one and pinned at the end: Ctrl-C midway left them unpinned, and a second
    `eval-split create` recorded them all again (under new ids) and pinned the copies, the first ones left as eval
    episodes nothing used (an operator's review)."""
    import workers.collect
    from tests.conftest import run_cli

    data = tmp_path / "data"
    real, calls = workers.collect.collect_episode, []

    def interrupted(*args, **kw):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kw)

    monkeypatch.setattr(workers.collect, "collect_episode", interrupted)
    tiny = ("--size", "16", "--steps", "3", "--data", str(data))
    assert run_cli(capsys, "eval-split", "create", "--episodes", "4", *tiny)[0] == 130  # (Ctrl-C's exit)
    first = {row.episode_id for row in Catalog(data).list(split="eval")}
    assert len(first) == 2 and Catalog(data).eval_split() is None
    monkeypatch.setattr(workers.collect, "collect_episode", real)
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", *tiny)
    split = Catalog(data).eval_split()
    assert rc == 0 and out.startswith("eval split pinned: 4 episodes") and "warning" not in err, err
    assert first <= set(split.ids) and Catalog(data).count(split="eval") == 4
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "4", *tiny)
    assert rc == 0 and out.startswith("eval split already pinned, with these settings: 4 episodes"), out
    # taken up with fewer episodes: the one left over is said, once the split is pinned
    data2, calls[:] = tmp_path / "data2", []
    monkeypatch.setattr(workers.collect, "collect_episode", interrupted)
    assert run_cli(capsys, "eval-split", "create", "--episodes", "4", *tiny[:4], "--data", str(data2))[0] == 130
    monkeypatch.setattr(workers.collect, "collect_episode", real)
    rc, out, err = run_cli(capsys, "eval-split", "create", "--episodes", "1", *tiny[:4], "--data", str(data2))
    assert rc == 0 and Catalog(data2).count(split="eval") == 2, (out, err)
    assert "warning: 1 eval episode(s) in " in err and "are not in the split" in err, err


def test_an_interrupted_eval_split_with_other_colours_is_not_taken_up(tmp_path, monkeypatch):
    """The metadata does not record a palette: the first frame tells an interrupted per-shape-colour split's
    episodes from the ones a default-colour create would record (a reviewer's reproduction pinned them)."""
    import workers.collect

    cat = Catalog(tmp_path / "data")
    real, calls = workers.collect.collect_episode, []

    def interrupted(*args, **kw):
        if kw.get("steps", 0) > 1:  # (not the one-step renders that check what is taken up)
            calls.append(1)
            if len(calls) == 3:
                raise KeyboardInterrupt
        return real(*args, **kw)

    monkeypatch.setattr(workers.collect, "collect_episode", interrupted)
    with pytest.raises(KeyboardInterrupt):
        create_eval_split(cat, episodes=4, seed=7, steps=3, image_size=16, palette=SHAPE_PALETTE)
    coloured = {row.episode_id for row in cat.list(split="eval")}
    monkeypatch.setattr(workers.collect, "collect_episode", real)
    create_eval_split(cat, episodes=4, seed=7, steps=3, image_size=16)
    pinned = set(cat.eval_split().ids)
    # T keeps the default colour in the palette: only its episode looks the same, and is taken up
    assert len(pinned & coloured) == sum(cat.meta(e).shape == "T" for e in coloured) < len(coloured)
