"""Collection policies: contact-rich pushing, seeded determinism, parameter validation."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.protocol import POLICIES, SHAPES, WORLD_SIZE
from tests.conftest import free_port, run_cli
from workers.env import PushEnv, PushSim, SimState, sample_state
from workers.policies import SIDES, make_policy


def rollout(policy: str, params, state: SimState, seed: int, steps: int = 50):
    sim = PushSim(16)
    sim.reset(state)
    pol = make_policy(policy, params, np.random.default_rng(seed))
    pol.reset(sim)
    actions, contacts = [], []
    for _ in range(steps):
        contacts.append(sim.in_contact())
        a = pol.act(sim)
        actions.append(a)
        sim.step(float(a[0]), float(a[1]))
    return np.stack(actions), np.array(contacts)


def test_push_policy_is_contact_rich_for_every_shape():
    rates = []
    for shape in SHAPES:
        for seed in range(2):
            state = sample_state(np.random.default_rng(100 + seed), shape=shape)
            _, contacts = rollout("push", None, state, seed)
            rates.append(contacts.mean())
    assert np.mean(rates) > 0.55, f"push episodes in contact: {np.round(rates, 2)}"
    assert min(rates) > 0.35, f"push episodes in contact: {np.round(rates, 2)}"


@pytest.mark.parametrize("side", list(SIDES))
def test_push_from_a_chosen_side_first_touches_from_that_side(side):
    state = SimState(shape="box", agent=(100.0, 440.0), obj=(256.0, 256.0, 0.0))
    sim = PushSim(16)
    sim.reset(state)
    pol = make_policy("push", {"side": side, "noise": 0.0}, np.random.default_rng(0))
    pol.reset(sim)
    for _ in range(40):
        if sim.in_contact():
            break
        sim.step(*pol.act(sim))
    assert sim.in_contact()
    s = sim.get_state()
    dx, dy = SIDES[side]
    # The pusher sits behind the object's centre as seen along the push direction.
    assert (s.agent[0] - s.obj[0]) * dx + (s.agent[1] - s.obj[1]) * dy < -20.0


def test_random_waypoints_moves_around_the_table():
    state = sample_state(np.random.default_rng(1), shape="T")
    actions, contacts = rollout("random_waypoints", {"hold": 3, "dwell": 0.3}, state, 4, steps=80)
    assert actions.dtype == np.float32 and actions.shape == (80, 2)
    assert ((actions >= 0) & (actions <= WORLD_SIZE)).all()
    distinct = {tuple(a) for a in actions}
    assert len(distinct) > 10
    assert contacts.mean() < 1.0  # (it roams: not every step touches the object)


def _runs(actions: np.ndarray) -> list[int]:
    """The lengths of the runs of equal consecutive actions."""
    runs = [1]
    for prev, cur in zip(actions[:-1], actions[1:]):
        if (prev == cur).all():
            runs[-1] += 1
        else:
            runs.append(1)
    return runs


def test_random_waypoints_holds_each_waypoint_at_most_hold_steps():
    state = sample_state(np.random.default_rng(2), shape="box")
    actions, _ = rollout("random_waypoints", {"hold": 3, "dwell": 0.0, "object_bias": 0.0}, state, 5, steps=200)
    runs = _runs(actions)
    assert max(runs) <= 3 and {2, 3} <= set(runs), runs  # (a waypoint is held 1 to 3 steps, drawn)


def test_random_waypoints_dwell_makes_the_next_waypoint_where_the_pusher_is():
    sim = PushSim(16)
    sim.reset(sample_state(np.random.default_rng(3), shape="T"))
    nudge = make_policy("random_waypoints", {"hold": 1, "dwell": 0.0}, np.random.default_rng(4))
    dwell = make_policy("random_waypoints", {"hold": 1, "dwell": 1.0}, np.random.default_rng(4))
    for step in range(30):
        if step % 3 == 0:  # (moved on now and then, so that where it is changes)
            sim.step(*(float(v) for v in nudge.act(sim)))
        at = sim.get_state().agent
        assert dwell.act(sim) == pytest.approx(np.array(at, np.float32)), step
        sim.step(*(float(v) for v in at))


@pytest.mark.parametrize("policy", POLICIES)
def test_policies_are_deterministic_for_a_seed(policy):
    state = sample_state(np.random.default_rng(9), shape="L")
    a1, _ = rollout(policy, None, state, seed=21, steps=30)
    a2, _ = rollout(policy, None, state, seed=21, steps=30)
    a3, _ = rollout(policy, None, state, seed=22, steps=30)
    assert a1.tobytes() == a2.tobytes()
    assert a1.tobytes() != a3.tobytes()


def test_policies_work_with_the_gymnasium_env():
    """A policy drives the gymnasium env: actions in its action space, observations in its observation space,
    and the pusher goes where the actions send it."""
    env = PushEnv(image_size=16, shape="disk")
    env.reset(seed=0)
    pol = make_policy("push", {"noise": 2.0}, np.random.default_rng(0))
    pol.reset(env)
    start = np.array(env.get_state().agent[:2])
    for _ in range(5):
        action = pol.act(env)
        assert env.action_space.contains(np.asarray(action, dtype=np.float32))
        obs, _, terminated, _, info = env.step(action)
        assert env.observation_space.contains(obs) and not terminated and isinstance(info["contact"], bool)
    assert not np.allclose(np.array(env.get_state().agent[:2]), start)


@pytest.mark.parametrize("name, params, match", [
    ("wander", None, "policy must be one of"),
    ("push", {"side": "up"}, "side"),
    ("push", {"side": ["left"]}, r"side must be one of .* found \['left'\]"),  # (a TypeError once: unhashable)
    ("push", {"side": {}}, "side must be one of"),
    ("push", {"side": 1}, "side must be one of"),
    ("push", {"noise": -1.0}, "noise"),
    ("push", {"speed": 3}, "unknown parameter"),
    ("random_waypoints", {"hold": 0}, "hold"),
    ("random_waypoints", {"dwell": "often"}, "dwell"),
])
def test_bad_policy_names_and_params_are_refused(name, params, match):
    with pytest.raises(ValueError, match=match):
        make_policy(name, params, np.random.default_rng(0))


@pytest.mark.parametrize("policy, params", [("random_waypoints", {"hold": 2.5}), ("push", {"push_steps": 7.5})])
def test_a_whole_number_parameter_refuses_a_fraction(policy, params):
    """2.5 would run as 2 and be recorded as 2: the episode would not be what its request asked for."""
    with pytest.raises(ValueError, match="whole number"):
        make_policy(policy, params, np.random.default_rng(0))
    whole = {k: float(int(v)) for k, v in params.items()}  # 2.0 (JSON may carry it so) is fine
    name, value = next(iter(whole.items()))
    assert make_policy(policy, whole, np.random.default_rng(0)).params[name] == int(value)


def test_queue_add_with_a_side_that_is_not_a_string_is_a_usage_error(capsys):
    """What the operator sees: one line and exit 2 before anything is sent (it was a TypeError traceback)."""
    rc, out, err = run_cli(capsys, "queue", "add", "--shape", "box", "--policy", "push", "--policy-params",
                           '{"side": []}', "--connect", f"tcp/127.0.0.1:{free_port()}", "--timeout", "1")
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "--policy-params: policy 'push': side must be one of" in err, err
