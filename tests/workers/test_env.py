"""The pushing simulator: exact reset, determinism, rendering, contact, validation, gymnasium API."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from orchestrator.protocol import PHYSICS_RANGES, SHAPES, WALL, WORLD_SIZE
from storage.records import STATE_DIM
from workers.env import (AGENT_RGB, OBJECT_RGB, SHAPE_PALETTE, PushEnv, PushSim, SimState, resolve_physics,
                         sample_state)
from workers.shapes import AGENT_RADIUS, get_shape


def moving_state(shape: str, rng: np.random.Generator) -> SimState:
    """A start state with non-zero velocities and non-default physics."""
    base = sample_state(rng, shape=shape, random_physics=True)
    return SimState(shape=shape, agent=base.agent, obj=base.obj, agent_vel=tuple(rng.normal(0, 80, 2)),
                    obj_vel=(*rng.normal(0, 50, 2), float(rng.normal(0, 2))), physics=base.physics)


def actions_for(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, WORLD_SIZE, (n, 2)).astype(np.float32)


def run(sim: PushSim, state: SimState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sim.reset(state)
    frames, states = [sim.render()], [sim.state_vector()]
    for a in actions:
        sim.step(float(a[0]), float(a[1]))
        frames.append(sim.render())
        states.append(sim.state_vector())
    return np.stack(frames), np.stack(states)


@pytest.mark.parametrize("shape", SHAPES)
def test_reset_puts_the_world_in_the_exact_state(shape):
    rng = np.random.default_rng(7)
    sim = PushSim(32)
    for _ in range(3):
        state = moving_state(shape, rng)
        sim.reset(state)
        back = sim.get_state()
        assert back.shape == shape and back.physics == state.physics
        np.testing.assert_allclose(back.to_vector(), state.to_vector(), rtol=0, atol=1e-6)
        assert back == state  # in fact bit-exact: nothing is stepped on reset
        vec = sim.state_vector()
        np.testing.assert_allclose(vec[:10], state.to_vector()[:10], rtol=0, atol=1e-6)


@pytest.mark.parametrize("shape", SHAPES)
def test_reset_after_steps_reproduces_a_mid_episode_state(shape):
    rng = np.random.default_rng(3)
    sim = PushSim(32)
    sim.reset(moving_state(shape, rng))
    for a in actions_for(1, 8):
        sim.step(*a)
    mid = sim.get_state()
    other = PushSim(32)
    other.reset(SimState.from_dict(json.loads(json.dumps(mid.to_dict()))))
    np.testing.assert_allclose(other.state_vector(), sim.state_vector(), rtol=0, atol=1e-6)


def test_same_start_and_actions_give_byte_identical_frames():
    rng = np.random.default_rng(11)
    for shape in SHAPES:
        state = moving_state(shape, rng)
        actions = actions_for(5, 25)
        f1, s1 = run(PushSim(48), state, actions)
        sim = PushSim(48)
        run(sim, moving_state(shape, rng), actions_for(6, 10))  # a reused sim forgets its past
        f2, s2 = run(sim, state, actions)
        assert f1.tobytes() == f2.tobytes()
        assert s1.tobytes() == s2.tobytes()
        assert not np.array_equal(f1[0], f1[-1])  # the pusher moved


def test_state_dict_round_trip_and_vector_order():
    state = sample_state(np.random.default_rng(0), shape="L")
    d = state.to_dict()
    assert set(d) == {"shape", "agent", "agent_vel", "object", "object_vel", "physics"}
    assert SimState.from_dict(json.loads(json.dumps(d))) == state
    vec = state.to_vector()
    assert vec.shape == (STATE_DIM,) and vec.dtype == np.float64
    assert list(vec[:2]) == list(state.agent) and list(vec[4:7]) == list(state.obj) and vec[10] == 0.0


def test_sample_state_covers_shapes_and_keeps_the_agent_off_the_object():
    rng = np.random.default_rng(2)
    states = [sample_state(rng) for _ in range(60)]
    assert {s.shape for s in states} == set(SHAPES)
    sim = PushSim(16)
    for s in states:
        assert s.physics == {k: v[2] for k, v in PHYSICS_RANGES.items()}
        sim.reset(s)
        assert not sim.in_contact()
    varied = sample_state(rng, random_physics=True).physics
    assert varied != states[0].physics and resolve_physics(varied) == varied


@pytest.mark.parametrize("bad, field", [
    ({"physics": {"mass": 99.0}}, "physics.mass"),
    ({"physics": {"mass": "heavy"}}, "physics.mass"),
    ({"physics": {"bounciness": 1.0}}, "bounciness"),
    ({"physics": {"ground_friction": 0.0}}, "physics.ground_friction"),
    ({"shape": "star"}, "shape"),
    ({"agent": [1.0]}, "agent"),
    ({"agent": [float("nan"), 3.0]}, "agent"),
    ({"object": [600.0, 100.0, 0.0]}, "object"),
    ({"object_vel": [0.0, 0.0, 1e9]}, "object_vel"),
    ({"colour": "red"}, "colour"),
])
def test_bad_states_and_physics_are_refused_naming_the_field(bad, field):
    d = {"shape": "T", "agent": [100.0, 100.0], "object": [256.0, 256.0, 0.5]}
    d.update(bad)
    with pytest.raises(ValueError, match=field):
        SimState.from_dict(d)


def test_missing_state_field_is_named():
    with pytest.raises(ValueError, match="object"):
        SimState.from_dict({"shape": "T", "agent": [100.0, 100.0]})
    with pytest.raises(ValueError, match="physics.friction"):
        PushEnv(physics={"friction": 5.0})


def test_contact_flag_follows_the_geometry():
    sim = PushSim(16)
    box = get_shape("box")
    half = box.rects[0][2]
    touching = SimState(shape="box", agent=(256.0 - half - AGENT_RADIUS + 0.5, 256.0), obj=(256.0, 256.0, 0.0))
    apart = SimState(shape="box", agent=(256.0 - half - AGENT_RADIUS - 5.0, 256.0), obj=(256.0, 256.0, 0.0))
    sim.reset(touching)
    assert sim.in_contact() and sim.state_vector()[10] == 1.0
    sim.reset(apart)
    assert not sim.in_contact() and sim.state_vector()[10] == 0.0
    sim.step(256.0, 256.0)  # drive through the box's centre: it must touch on the way
    touched = sim.in_contact()
    for _ in range(3):
        sim.step(256.0, 256.0)
        touched = touched or sim.in_contact()
    assert touched


@pytest.mark.parametrize("size", [16, 64, 96])
def test_frames_are_rgb_uint8_with_pusher_and_object_visible(size):
    sim = PushSim(size)
    sim.reset(SimState(shape="T", agent=(100.0, 100.0), obj=(300.0, 300.0, 0.3)))
    frame = sim.render()
    assert frame.shape == (size, size, 3) and frame.dtype == np.uint8
    assert (frame == np.array(OBJECT_RGB, np.uint8)).all(-1).any()
    if size >= 64:
        assert (frame == np.array(AGENT_RGB, np.uint8)).all(-1).any()
    # y points up: the pusher (low y) is drawn in the lower half of the image.
    agent_rows = np.nonzero((np.abs(frame.astype(int) - AGENT_RGB).sum(-1) < 60).any(1))[0]
    assert agent_rows.min() > size // 2
    out = np.zeros_like(frame)
    assert sim.render_into(out) is out and np.array_equal(out, frame)


def test_object_pushed_against_a_wall_stays_inside():
    sim = PushSim(16)
    geom = get_shape("box")
    start = SimState(shape="box", agent=(256.0, 150.0), obj=(256.0, 80.0, 0.0), physics={"mass": 0.2})
    sim.reset(start)
    for _ in range(30):
        sim.step(256.0, 0.0)  # keep pushing down into the bottom wall
    x, y, theta = sim.get_state().obj
    c, s = math.cos(theta), math.sin(theta)
    lowest = y + min(vx * s + vy * c for vx, vy in geom.outline)
    assert lowest > WALL - 3.0, f"box sank {WALL - lowest:.1f} units into the bottom wall"
    assert sim.in_contact()


@pytest.mark.filterwarnings("ignore:.*symmetric and normalized space")  # actions are table positions
@pytest.mark.filterwarnings("ignore:.*not having a spec")
def test_gymnasium_check_env_passes():
    env = PushEnv(image_size=32, shape=None, max_steps=5)
    check_env(env, skip_render_check=False)
    obs, info = env.reset(seed=3)
    assert obs.shape == (32, 32, 3) and "contact" in info
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert truncated and not terminated and reward == 0.0


def test_env_reset_with_state_option_and_state_accessors():
    env = PushEnv(image_size=16)
    state = moving_state("disk", np.random.default_rng(4))
    obs, _ = env.reset(options={"state": state.to_dict()})
    assert env.get_state() == state
    np.testing.assert_array_equal(obs, env.render())
    assert env.state_vector().shape == (STATE_DIM,)
    assert isinstance(env.in_contact(), bool)
    with pytest.raises(ValueError, match="action"):
        env.step([math.nan, 1.0])


def test_a_palette_recolours_only_the_shapes_it_names():
    state = SimState(shape="L", agent=(100.0, 100.0), obj=(300.0, 300.0, 0.3))
    plain, coloured = PushSim(64), PushSim(64, palette={"L": SHAPE_PALETTE["L"]})
    plain.reset(state)
    coloured.reset(state)
    a, b = plain.render(), coloured.render()
    assert (a == np.array(OBJECT_RGB, np.uint8)).all(-1).any() and not (b == OBJECT_RGB).all(-1).any()
    assert (b == np.array(SHAPE_PALETTE["L"], np.uint8)).all(-1).any()
    agent = (a == np.array(AGENT_RGB, np.uint8)).all(-1)
    assert agent.any() and (b[agent] == AGENT_RGB).all()  # the pusher keeps its colour
    t = SimState(shape="T", agent=(100.0, 100.0), obj=(300.0, 300.0, 0.3))
    plain.reset(t)
    coloured.reset(t)
    assert np.array_equal(plain.render(), coloured.render())


@pytest.mark.parametrize("palette, message", [({"star": (1, 2, 3)}, "unknown shape"),
                                              ({"T": (1, 2)}, "three ints"), ({"T": (1, 2, 300)}, "three ints")])
def test_a_bad_palette_is_refused(palette, message):
    with pytest.raises(ValueError, match=message):
        PushSim(16, palette=palette)
