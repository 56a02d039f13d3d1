"""Collection policies: what the pusher does while an episode is recorded.

A policy is built by ``make_policy(name, params, rng)`` and used as
``policy.reset(env)`` once, then ``policy.act(env) -> (2,) float32`` per step.
``env`` is anything with ``get_state() -> SimState`` (``PushEnv`` or
``PushSim``). All randomness comes from the generator passed
in, so one seed gives one action sequence for one start state.
"""

from __future__ import annotations

import json
import math
from typing import Any, Mapping, Protocol

import numpy as np

from orchestrator.protocol import AGENT_RANGE, POLICIES, WALL, WORLD_SIZE
from workers.env import SimState
from workers.shapes import AGENT_RADIUS, get_shape

#: Sides the push policy can approach from, as the direction it then pushes in.
SIDES: dict[str, tuple[float, float]] = {
    "left": (1.0, 0.0), "right": (-1.0, 0.0), "top": (0.0, -1.0), "bottom": (0.0, 1.0),
}


class SimLike(Protocol):
    def get_state(self) -> SimState: ...


class Policy(Protocol):
    """A collection policy: ``reset(env)`` at the episode's start, then ``act(env)`` per step."""

    def reset(self, env: SimLike) -> None: ...
    def act(self, env: SimLike) -> np.ndarray: ...


def _params(name: str, given: Mapping[str, Any] | None, defaults: dict[str, Any]) -> dict[str, Any]:
    given = dict(given or {})
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise ValueError(f"policy {name!r}: unknown parameter(s) {unknown}, expected {sorted(defaults)}")
    return {**defaults, **given}


def _number(policy: str, key: str, value: Any, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"policy {policy!r}: {key} must be a number, found {value!r}")
    if not (low <= float(value) <= high):
        raise ValueError(f"policy {policy!r}: {key} must be in [{low}, {high}], found {value}")
    return float(value)


def _integer(policy: str, key: str, value: Any, low: int, high: int) -> int:
    """A whole number (2 or 2.0; not 2.5, which would be recorded as something it was not asked)."""
    number = _number(policy, key, value, low, high)
    if number != int(number):
        raise ValueError(f"policy {policy!r}: {key} must be a whole number, found {value}")
    return int(number)


def _target(x: float, y: float) -> np.ndarray:
    return np.array((min(max(x, 0.0), WORLD_SIZE), min(max(y, 0.0), WORLD_SIZE)), np.float32)


class RandomWaypoints:
    """Moves to random targets and holds each for a few steps; sometimes dwells in place.

    Params: ``hold`` (max steps per waypoint, >= 1), ``dwell`` (probability a new waypoint is the
    current position), ``object_bias`` (probability a waypoint lies just past the object's
    centre, as seen from the pusher, so that random data also contains pushes).
    """

    DEFAULTS = {"hold": 6, "dwell": 0.15, "object_bias": 0.3}

    def __init__(self, params: Mapping[str, Any] | None, rng: np.random.Generator) -> None:
        p = _params("random_waypoints", params, self.DEFAULTS)
        self.hold = _integer("random_waypoints", "hold", p["hold"], 1, 1000)
        self.dwell = _number("random_waypoints", "dwell", p["dwell"], 0.0, 1.0)
        self.object_bias = _number("random_waypoints", "object_bias", p["object_bias"], 0.0, 1.0)
        self.params = {"hold": self.hold, "dwell": self.dwell, "object_bias": self.object_bias}
        self.rng = rng
        self._left = 0
        self._goal = np.zeros(2, np.float32)

    def reset(self, env: SimLike) -> None:
        self._left = 0

    def act(self, env: SimLike) -> np.ndarray:
        if self._left <= 0:
            s = env.get_state()
            u = self.rng.random()
            if u < self.dwell:
                self._goal = _target(*s.agent)
            elif u < self.dwell + self.object_bias:
                ox, oy = s.obj[0], s.obj[1]
                dx, dy = ox - s.agent[0], oy - s.agent[1]
                norm = math.hypot(dx, dy) or 1.0
                reach = self.rng.uniform(20.0, 80.0)
                self._goal = _target(ox + dx / norm * reach, oy + dy / norm * reach)
            else:
                self._goal = _target(*self.rng.uniform(*AGENT_RANGE, size=2))
            self._left = int(self.rng.integers(1, self.hold + 1))
        self._left -= 1
        return self._goal.copy()


class Push:
    """Approaches the object from one side, then pushes through its centre, with noise.

    Approach: goes round the object (outside its bounding circle) to the point just behind it
    in the push direction. Push: each step aims ``stride`` units past the object's near side
    (closing any gap to an object that slid ahead), towards its centre, plus Gaussian noise of
    ``noise`` units; re-aiming at the centre every step keeps the pusher in contact. A push
    ends after ``push_steps`` steps, when the object nears a wall in the push direction, or
    when the pusher has been more than 10 units off it for three steps; the next push
    direction points roughly at the table's centre (within ~35 degrees, drawn).

    Params: ``side`` (left/right/top/bottom: the first push comes from there when the pusher fits
    behind the object on that side; with the object against that wall the first direction is
    drawn as for None, and the recorded params still say what was asked; None draws it),
    ``noise`` (world units, >= 0), ``stride`` (world units), ``push_steps`` (max steps per push).
    """

    DEFAULTS = {"side": None, "noise": 6.0, "stride": 25.0, "push_steps": 30}
    _LO, _HI = WALL + AGENT_RADIUS, WORLD_SIZE - WALL - AGENT_RADIUS

    def __init__(self, params: Mapping[str, Any] | None, rng: np.random.Generator) -> None:
        p = _params("push", params, self.DEFAULTS)
        if p["side"] is not None and (not isinstance(p["side"], str) or p["side"] not in SIDES):  # [] is unhashable
            raise ValueError(f"policy 'push': side must be one of {list(SIDES)} or None, found {p['side']!r}")
        self.side = p["side"]
        self.noise = _number("push", "noise", p["noise"], 0.0, 200.0)
        self.stride = _number("push", "stride", p["stride"], 1.0, 200.0)
        self.push_steps = _integer("push", "push_steps", p["push_steps"], 1, 1000)
        self.params = {"side": self.side, "noise": self.noise, "stride": self.stride,
                       "push_steps": self.push_steps}
        self.rng = rng

    def reset(self, env: SimLike) -> None:
        s = env.get_state()
        self._geom = get_shape(s.shape)
        self._outline = [(float(x), float(y)) for x, y in self._geom.outline]
        self._clear = self._geom.bounding_radius + AGENT_RADIUS + 4.0
        if self.side is not None and self._goal(s, SIDES[self.side])[1]:
            self._start_approach(SIDES[self.side])
        else:
            self._start_approach(self._pick_dir(s))

    def act(self, env: SimLike) -> np.ndarray:
        s = env.get_state()
        if self._phase == "push":
            target = self._push(s)
            if target is not None:
                return target
            self._start_approach(self._pick_dir(s))
        self._approach_left -= 1
        if self._approach_left < 0:
            self._start_approach(self._pick_dir(s))
        return self._approach(s)

    def _start_approach(self, direction: tuple[float, float]) -> None:
        self._dir = direction
        self._phase = "approach"
        self._left = self.push_steps
        self._lost = -1  # -1 until the push first touches the object
        self._approach_left = 15
        self._turn = 0.0  # which way round the object the approach goes (+1 ccw, -1 cw)

    def _extent(self, s: SimState, ux: float, uy: float) -> float:
        """How far the object reaches from its centre in direction (ux, uy)."""
        if not self._geom.rects:
            return self._geom.radius
        c, sn = math.cos(s.obj[2]), math.sin(s.obj[2])
        lx, ly = c * ux + sn * uy, -sn * ux + c * uy  # the direction in the object's frame
        return max(x * lx + y * ly for x, y in self._outline)

    def _gap(self, s: SimState) -> float:
        """Distance from the pusher's rim to the object's boundary."""
        c, sn = math.cos(s.obj[2]), math.sin(s.obj[2])
        dx, dy = s.agent[0] - s.obj[0], s.agent[1] - s.obj[1]
        return self._geom.distance(c * dx + sn * dy, -sn * dx + c * dy) - AGENT_RADIUS

    def _goal(self, s: SimState, direction: tuple[float, float]) -> tuple[tuple[float, float], bool]:
        """The approach point behind the object for ``direction``, and whether the pusher fits there."""
        dx, dy = direction
        back = self._extent(s, -dx, -dy) + AGENT_RADIUS + 4.0
        gx, gy = s.obj[0] - dx * back, s.obj[1] - dy * back
        return (gx, gy), self._LO <= gx <= self._HI and self._LO <= gy <= self._HI

    def _pick_dir(self, s: SimState) -> tuple[float, float]:
        """A push direction roughly towards the table's centre whose approach point is reachable."""
        cx, cy = WORLD_SIZE / 2 - s.obj[0], WORLD_SIZE / 2 - s.obj[1]
        centre = math.atan2(cy, cx) if math.hypot(cx, cy) > 40.0 else None
        best = (1.0, 0.0)
        for i in range(8):
            if centre is None or i >= 6:
                a = self.rng.uniform(-math.pi, math.pi)
            else:
                a = centre + self.rng.normal(0.0, math.radians(35))
            best = (math.cos(a), math.sin(a))
            if self._goal(s, best)[1]:
                break
        return best

    def _approach(self, s: SimState) -> np.ndarray:
        (ax, ay), (ox, oy) = s.agent, s.obj[:2]
        (gx, gy), _ = self._goal(s, self._dir)
        if math.hypot(gx - ax, gy - ay) < 20.0:
            self._phase = "push"
            return self._push_target(s)
        a_agent = math.atan2(ay - oy, ax - ox)
        a_goal = math.atan2(gy - oy, gx - ox)
        diff = (a_goal - a_agent + math.pi) % (2 * math.pi) - math.pi
        if abs(diff) > math.radians(45) and _segment_distance(ox, oy, ax, ay, gx, gy) < self._clear:
            # The straight way crosses the object: go round it on its clearance circle.
            # Keep one way round per approach (the shorter one, unless a wall blocks it) so
            # the pusher does not dither between the two.
            r = max(self._clear, math.hypot(ax - ox, ay - oy)) + 10.0
            turn = min(abs(diff), math.radians(60))
            if self._turn == 0.0:
                self._turn = math.copysign(1.0, diff)
                a = a_agent + self._turn * turn
                wx, wy = ox + r * math.cos(a), oy + r * math.sin(a)
                if not (self._LO <= wx <= self._HI and self._LO <= wy <= self._HI):
                    self._turn = -self._turn
            if self._turn != math.copysign(1.0, diff):
                turn = math.radians(60)  # the long way round
            a = a_agent + self._turn * turn
            wx, wy = ox + r * math.cos(a), oy + r * math.sin(a)
            return self._inside(wx, wy)
        return self._inside(gx, gy)

    def _push(self, s: SimState) -> np.ndarray | None:
        self._left -= 1
        if self._gap(s) <= 10.0:  # touching, or close behind an object sliding ahead
            self._lost = 0
        elif self._lost >= 0:
            self._lost += 1
        if self._left <= 0 or self._lost > 2 or self._blocked(s):
            return None
        return self._push_target(s)

    def _blocked(self, s: SimState) -> bool:
        """Whether the object is about to hit a wall in the current push direction."""
        (ax, ay), (ox, oy) = s.agent, s.obj[:2]
        dx, dy = ox - ax, oy - ay
        norm = math.hypot(dx, dy) or 1.0
        ux, uy = dx / norm, dy / norm
        margin = WALL + 10.0
        if abs(ux) > 0.3:
            sx = math.copysign(1.0, ux)
            if not margin < ox + sx * self._extent(s, sx, 0.0) < WORLD_SIZE - margin:
                return True
        if abs(uy) > 0.3:
            sy = math.copysign(1.0, uy)
            if not margin < oy + sy * self._extent(s, 0.0, sy) < WORLD_SIZE - margin:
                return True
        return False

    def _push_target(self, s: SimState) -> np.ndarray:
        (ax, ay), (ox, oy) = s.agent, s.obj[:2]
        dx, dy = ox - ax, oy - ay
        norm = math.hypot(dx, dy) or 1.0
        ux, uy = dx / norm, dy / norm
        # Close any gap first (a sliding object runs ahead), then press on by `stride`.
        reach = max(self._gap(s), 0.0) + self.stride
        nx, ny = self.rng.normal(0.0, self.noise, size=2) if self.noise > 0 else (0.0, 0.0)
        return self._inside(ax + ux * reach + nx, ay + uy * reach + ny)

    @classmethod
    def _inside(cls, x: float, y: float) -> np.ndarray:
        return _target(min(max(x, cls._LO), cls._HI), min(max(y, cls._LO), cls._HI))


def _segment_distance(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    """Distance from point p to the segment a-b."""
    vx, vy = bx - ax, by - ay
    length2 = vx * vx + vy * vy
    t = 0.0 if length2 == 0.0 else min(max(((px - ax) * vx + (py - ay) * vy) / length2, 0.0), 1.0)
    return math.hypot(px - ax - t * vx, py - ay - t * vy)


_REGISTRY = {"random_waypoints": RandomWaypoints, "push": Push}
if tuple(_REGISTRY) != POLICIES:
    raise RuntimeError(f"policies.py defines {list(_REGISTRY)} but protocol.POLICIES is {list(POLICIES)}")


def make_policy(name: str, params: Mapping[str, Any] | None, rng: np.random.Generator) -> Policy:
    """Builds policy ``name`` with ``params`` and generator ``rng``.

    Raises ValueError for an unknown name, an unknown parameter or a bad value.
    """
    try:
        cls = _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"policy must be one of {list(POLICIES)}, found {name!r}") from None
    return cls(params, rng)


def check_policy_params(name: str, params: Mapping[str, Any] | None) -> None:
    """ValueError, as ``make_policy`` raises it, unless policy ``name`` takes ``params``: what a request is checked
    with before it is queued, so that no worker refuses it later."""
    make_policy(name, params, np.random.default_rng(0))


def policy_params_help() -> str:
    """Each policy's parameters with their defaults as JSON, for a ``--help``."""
    return "; ".join(f"{name}: " + ", ".join(f"{k}={json.dumps(v)}" for k, v in cls.DEFAULTS.items())
                     for name, cls in _REGISTRY.items())
