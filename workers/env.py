"""The pushing simulator: a pymunk 7 world, its exact state, an OpenCV renderer and a gymnasium Env.

Top-down table (no gravity) of ``WORLD_SIZE`` units with walls; y points up,
the origin is the bottom-left corner. A disk pusher follows the action target
(an absolute position) through a PD controller at 10 Hz with 10 physics
substeps per action, with PushT's gains. The pushed object slides on the table
with Coulomb-like ground friction: a pivot joint and a gear joint to the static
body with ``max_bias = 0`` cap the linear and angular friction impulses (the
top-down friction of pymunk's tank example), scaled by
``ground_friction * mass``.

The pusher is a heavy dynamic body (``AGENT_MASS``, no rotation) whose PD
acceleration is applied as a force, not a kinematic body as in PushT: in free
motion the two integrate identically (up to our speed cap, ``MAX_AGENT_SPEED``),
but a kinematic (infinite-mass) pusher squeezes an object caught against a wall
straight through it (about one episode in ten with random waypoints), while a
finite mass is stopped by it.

``PushSim`` is the simulator itself (reset to a ``SimState``, step, read state,
render into a buffer); ``PushEnv`` wraps it as a ``gymnasium.Env``. Every reset
rebuilds the pymunk space, so the same start state and actions give the same
frames, byte for byte. A state read mid-episode and reset to does not go on
exactly as the recording did where the pusher touches the object: pymunk keeps
contact and friction impulses between steps, which ``SimState`` does not hold
and a rebuilt space starts without (of 480 resets to recorded states with their
velocities, 6 were more than 1 unit off after one step, 31 after twenty). A
reset at rest, as the planner's requests are by default, starts exactly at the
state asked for, and a replayed prefix reaches it exactly (0.0 over 1,989
requests): where a transition itself must be reproduced, replay the prefix
(``ActivePlannerConfig.replay_prefix``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import cv2
import gymnasium as gym
import numpy as np
import pymunk
from pymunk._chipmunk import lib as _cp

from orchestrator.protocol import (AGENT_RANGE, OBJECT_RANGE, PHYSICS_RANGES, SHAPES, WALL,
                                   WORLD_SIZE)
from storage.records import MAX_FRAME_SIZE, MIN_FRAME_SIZE, STATE_DIM
from workers.shapes import AGENT_RADIUS, ShapeGeometry, get_shape

#: Actions per simulated second and physics substeps per action.
CONTROL_HZ = 10
SUBSTEPS = 10
#: PD gains of the pusher (PushT's): acceleration = KP * (target - p) - KV * v.
KP = 100.0
KV = 20.0
#: Largest pusher speed (units / s): 8 units per substep, well under the objects' 30-unit width.
MAX_AGENT_SPEED = 800.0
#: Mass of the pusher: heavy enough to push any object (mass <= 5) near PD speed, finite so that
#: an object caught against a wall stops it instead of being squeezed through the wall.
AGENT_MASS = 10.0
#: Normal acceleration that turns ``ground_friction * mass`` into a friction force (units / s^2).
TABLE_GRAVITY = 981.0
#: Pusher and object count as touching when their gap is at most this (world units).
CONTACT_TOLERANCE = 1.0
#: Largest speed a state may carry (units / s, rad / s); beyond it a state is refused.
MAX_SPEED = 1.0e4
#: Friction of the pusher's surface and of the walls (pymunk multiplies the two sides).
AGENT_FRICTION = 1.0
WALL_FRICTION = 0.5

TABLE_RGB = (236, 232, 222)
WALL_RGB = (52, 54, 60)
OBJECT_RGB = (86, 110, 150)
MARKER_RGB = (46, 62, 92)
AGENT_RGB = (222, 92, 48)
#: A world where the objects also differ in colour (``PushSim(palette=SHAPE_PALETTE)``): used by the
#: out-of-distribution experiment in bench/uncertainty_figures.py; the service draws every object in
#: ``OBJECT_RGB``.
SHAPE_PALETTE = {"T": OBJECT_RGB, "L": (64, 140, 84), "box": (146, 92, 160), "disk": (184, 142, 48)}
_SHIFT = 4  # sub-pixel bits for cv2 drawing
_ONE = 1 << _SHIFT


def resolve_physics(physics: Mapping[str, float] | None) -> dict[str, float]:
    """Fills defaults and validates physics parameters against ``PHYSICS_RANGES``.

    Raises ValueError naming the parameter that is unknown, not a number or out of range.
    """
    physics = dict(physics or {})
    unknown = sorted(set(physics) - set(PHYSICS_RANGES))
    if unknown:
        raise ValueError(f"physics: unknown parameter(s) {unknown}, expected {sorted(PHYSICS_RANGES)}")
    out: dict[str, float] = {}
    for name, (low, high, default) in PHYSICS_RANGES.items():
        value = physics.get(name, default)
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
            raise ValueError(f"physics.{name}: expected a number, found {value!r}")
        value = float(value)
        if not (low <= value <= high):
            raise ValueError(f"physics.{name}: expected {low} <= value <= {high}, found {value}")
        out[name] = value
    return out


def _floats(name: str, value: Any, n: int, low: float, high: float) -> tuple[float, ...]:
    try:
        items = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {n} numbers, found {value!r}") from None
    if len(items) != n:
        raise ValueError(f"{name}: expected {n} numbers, found {len(items)}")
    for v in items:
        if not (math.isfinite(v) and low <= v <= high):
            raise ValueError(f"{name}: expected finite values in [{low}, {high}], found {list(items)}")
    return items


@dataclass(kw_only=True)
class SimState:
    """The simulator state ``PushSim.reset`` takes and ``get_state`` returns (keywords only): poses, velocities,
    physics; not pymunk's contact impulses, so a reset mid-contact goes on slightly otherwise (module docstring)."""

    shape: str
    """Object shape, one of ``SHAPES``."""
    agent: tuple[float, float]
    """Pusher centre (x, y) in world units."""
    obj: tuple[float, float, float]
    """Object centre of mass (x, y) and angle theta (rad, not wrapped)."""
    agent_vel: tuple[float, float] = (0.0, 0.0)
    """Pusher velocity (vx, vy)."""
    obj_vel: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Object velocity (vx, vy) and angular velocity omega."""
    physics: dict[str, float] = field(default_factory=dict)
    """mass, friction, ground_friction (defaults filled in)."""

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"shape: expected one of {list(SHAPES)}, found {self.shape!r}")
        self.agent = _floats("agent", self.agent, 2, 0.0, WORLD_SIZE)
        obj = _floats("object", self.obj, 3, -math.inf, math.inf)
        _floats("object", obj[:2], 2, 0.0, WORLD_SIZE)
        self.obj = obj
        self.agent_vel = _floats("agent_vel", self.agent_vel, 2, -MAX_SPEED, MAX_SPEED)
        self.obj_vel = _floats("object_vel", self.obj_vel, 3, -MAX_SPEED, MAX_SPEED)
        self.physics = resolve_physics(self.physics)

    @classmethod
    def trusted(cls, shape: str, agent: tuple[float, float], agent_vel: tuple[float, float],
                obj: tuple[float, float, float], obj_vel: tuple[float, float, float],
                physics: dict[str, float]) -> "SimState":
        """Builds a state without validation: for values read back from a running simulator."""
        state = object.__new__(cls)
        state.shape, state.agent, state.agent_vel = shape, agent, agent_vel
        state.obj, state.obj_vel, state.physics = obj, obj_vel, physics
        return state

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: {"shape", "agent", "agent_vel", "object", "object_vel", "physics"}."""
        return {
            "shape": self.shape, "agent": list(self.agent), "agent_vel": list(self.agent_vel),
            "object": list(self.obj), "object_vel": list(self.obj_vel), "physics": dict(self.physics),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SimState":
        """Parses ``to_dict``'s form; velocities and physics may be left out (zero / defaults).

        Raises ValueError naming the missing, unknown or bad field.
        """
        if not isinstance(d, Mapping):
            raise ValueError(f"state: expected an object, found {type(d).__name__}")
        known = {"shape", "agent", "agent_vel", "object", "object_vel", "physics"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"state: unknown field(s) {unknown}, expected {sorted(known)}")
        for name in ("shape", "agent", "object"):
            if name not in d:
                raise ValueError(f"state: missing field {name!r}")
        physics = d.get("physics") or {}
        if not isinstance(physics, Mapping):
            raise ValueError(f"physics: expected an object, found {type(physics).__name__}")
        return cls(shape=d["shape"], agent=d["agent"], obj=d["object"],
                   agent_vel=d.get("agent_vel", (0.0, 0.0)), obj_vel=d.get("object_vel", (0.0, 0.0, 0.0)),
                   physics=physics)

    def to_vector(self, contact: bool = False) -> np.ndarray:
        """(11,) float64 in ``storage.records.STATE_FIELDS`` order; contact is given by the caller."""
        return np.array([*self.agent, *self.agent_vel, *self.obj, *self.obj_vel, float(contact)])


def sample_state(rng: np.random.Generator, shape: str | None = None,
                 physics: Mapping[str, float] | None = None, random_physics: bool = False) -> SimState:
    """A start state drawn uniformly from the task space, at rest.

    Object centre uniform in ``OBJECT_RANGE``^2 with a uniform angle; pusher uniform in
    ``AGENT_RANGE``^2, redrawn until it does not touch the object. ``shape=None`` draws a shape;
    ``physics`` fixes parameters (the rest default, or are drawn uniformly with ``random_physics``).
    """
    if shape is None:
        shape = SHAPES[int(rng.integers(len(SHAPES)))]
    geom = get_shape(shape)
    chosen = dict(physics or {})
    if random_physics:
        for name, (low, high, _) in PHYSICS_RANGES.items():
            chosen.setdefault(name, float(rng.uniform(low, high)))
    x, y = rng.uniform(*OBJECT_RANGE, size=2)
    theta = rng.uniform(-math.pi, math.pi)
    c, s = math.cos(theta), math.sin(theta)
    while True:
        ax, ay = rng.uniform(*AGENT_RANGE, size=2)
        dx, dy = ax - x, ay - y
        if geom.distance(c * dx + s * dy, -s * dx + c * dy) > AGENT_RADIUS + 2 * CONTACT_TOLERANCE:
            break
    return SimState(shape=shape, agent=(float(ax), float(ay)), obj=(float(x), float(y), float(theta)),
                    physics=chosen)


def _check_palette(palette: Mapping[str, tuple[int, int, int]] | None) -> dict[str, tuple[int, int, int]]:
    """Every shape's object colour: ``palette``'s where it names one, ``OBJECT_RGB`` elsewhere."""
    out = dict.fromkeys(SHAPES, OBJECT_RGB)
    for shape, rgb in (palette or {}).items():
        if shape not in SHAPES:
            raise ValueError(f"palette: unknown shape {shape!r}, expected some of {list(SHAPES)}")
        if (not isinstance(rgb, (tuple, list)) or len(rgb) != 3
                or not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in rgb)):
            raise ValueError(f"palette[{shape!r}]: expected three ints in [0, 255], found {rgb!r}")
        out[shape] = tuple(rgb)
    return out


@functools.lru_cache(maxsize=8)
def _background(size: int) -> np.ndarray:
    """Table and walls, drawn at 8x and area-averaged so the wall edges are anti-aliased."""
    big = 8 * size
    img = np.full((big, big, 3), TABLE_RGB, np.uint8)
    w = int(round(WALL / WORLD_SIZE * big))
    for sl in (np.s_[:w, :], np.s_[-w:, :], np.s_[:, :w], np.s_[:, -w:]):
        img[sl] = WALL_RGB
    out = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=8)
def scene_colours(size: int) -> tuple[tuple[int, int, int], ...]:
    """Every colour a frame of ``size`` px holds besides the object's: the table's, the walls' and their
    anti-aliased edges at that size, and the pusher's."""
    table_and_walls = {tuple(int(c) for c in rgb) for rgb in np.unique(_background(size).reshape(-1, 3), axis=0)}
    return tuple(sorted(table_and_walls | {AGENT_RGB}))


class PushSim:
    """The pushing world without the gymnasium wrapper: reset, step, state, contact, render.

    The per-substep loop calls Chipmunk through pymunk's cffi ``lib`` (pymunk 7's own
    binding, which ``pymunk.Body``'s properties wrap): the wrappers' attribute hooks cost
    about 1 us per access, which was a third of a recorded frame.
    """

    def __init__(self, image_size: int = 64, palette: Mapping[str, tuple[int, int, int]] | None = None) -> None:
        """``palette``: object colour (RGB) per shape; shapes it leaves out are drawn in ``OBJECT_RGB``."""
        if (isinstance(image_size, bool) or not isinstance(image_size, int)
                or not MIN_FRAME_SIZE <= image_size <= MAX_FRAME_SIZE):
            raise ValueError(f"image_size: expected an int in [{MIN_FRAME_SIZE}, {MAX_FRAME_SIZE}], "
                             f"found {image_size!r}")
        self.image_size = image_size
        self._palette = _check_palette(palette)
        self._bg = _background(image_size)
        self._k = image_size / WORLD_SIZE * _ONE  # world units -> fixed-point pixels
        self._space: pymunk.Space | None = None
        self._state: SimState | None = None
        self._snap: tuple[float, ...] | None = None

    # -- world ---------------------------------------------------------------------------------
    def reset(self, state: SimState) -> None:
        """Rebuilds the world in exactly ``state`` (no physics step is taken)."""
        if not isinstance(state, SimState):
            raise TypeError(f"reset: expected a SimState, found {type(state).__name__}")
        geom = get_shape(state.shape)
        mass, friction, ground = (state.physics[k] for k in ("mass", "friction", "ground_friction"))
        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        static = space.static_body
        far = WORLD_SIZE + 100.0  # thick walls so a hard push cannot tunnel through them
        walls = [pymunk.Poly(static, [(a, b), (c, b), (c, d), (a, d)]) for a, b, c, d in (
            (-100.0, -100.0, far, WALL), (-100.0, WORLD_SIZE - WALL, far, far),
            (-100.0, -100.0, WALL, far), (WORLD_SIZE - WALL, -100.0, far, far))]
        for w in walls:
            w.friction = WALL_FRICTION
        agent = pymunk.Body(AGENT_MASS, math.inf)
        agent.position = state.agent
        agent.velocity = state.agent_vel
        disk = pymunk.Circle(agent, AGENT_RADIUS)
        disk.friction = AGENT_FRICTION
        body = pymunk.Body(mass, mass * geom.moment_per_mass)
        body.position = state.obj[:2]
        body.angle = state.obj[2]
        body.velocity = state.obj_vel[:2]
        body.angular_velocity = state.obj_vel[2]
        if geom.rects:
            parts = [pymunk.Poly(body, [tuple(v) for v in verts]) for verts in geom.parts()]
        else:
            parts = [pymunk.Circle(body, geom.radius)]
        for p in parts:
            p.friction = friction
        pivot = pymunk.PivotJoint(static, body, (0.0, 0.0), (0.0, 0.0))
        pivot.max_bias = 0.0
        pivot.max_force = ground * mass * TABLE_GRAVITY
        gear = pymunk.GearJoint(static, body, 0.0, 1.0)
        gear.max_bias = 0.0
        gear.max_force = ground * mass * TABLE_GRAVITY * geom.friction_radius
        space.add(*walls, agent, disk, body, *parts, pivot, gear)
        self._space, self._agent, self._body, self._geom = space, agent, body, geom
        self._cp_space, self._cp_agent, self._cp_body = space._space, agent._body, body._body
        self._state = state
        self._snap = None

    def step(self, target_x: float, target_y: float) -> None:
        """Drives the pusher towards (target_x, target_y) for one control period (10 substeps).

        The target is clamped inside the walls. The controller runs in plain floats; the
        pusher's force is the only thing set per substep. (Nothing here uses pymunk's
        callbacks or removals, which is all ``Space.step`` adds around ``cpSpaceStep``.)
        """
        self._require()
        lo, hi = WALL + AGENT_RADIUS, WORLD_SIZE - WALL - AGENT_RADIUS
        tx = min(max(float(target_x), lo), hi)
        ty = min(max(float(target_y), lo), hi)
        dt = 1.0 / (CONTROL_HZ * SUBSTEPS)
        kp_dt, keep, vmax2, f_per_dv = KP * dt, 1.0 - KV * dt, MAX_AGENT_SPEED**2, AGENT_MASS / dt
        space, agent = self._cp_space, self._cp_agent
        set_force, get_pos, get_vel, space_step = (
            _cp.cpBodySetForce, _cp.cpBodyGetPosition, _cp.cpBodyGetVelocity, _cp.cpSpaceStep)
        p, v = get_pos(agent), get_vel(agent)
        px, py, vx, vy = p.x, p.y, v.x, v.y
        for _ in range(SUBSTEPS):
            # PD: v' = v + (KP (target - p) - KV v) dt, capped so the pusher cannot tunnel
            # through an object in one substep; applied as the force that makes that change.
            nvx = vx * keep + kp_dt * (tx - px)
            nvy = vy * keep + kp_dt * (ty - py)
            speed2 = nvx * nvx + nvy * nvy
            if speed2 > vmax2:
                scale = MAX_AGENT_SPEED / math.sqrt(speed2)
                nvx, nvy = nvx * scale, nvy * scale
            set_force(agent, (f_per_dv * (nvx - vx), f_per_dv * (nvy - vy)))
            space_step(space, dt)
            p, v = get_pos(agent), get_vel(agent)
            px, py, vx, vy = p.x, p.y, v.x, v.y
        self._snap = None

    def _read(self) -> tuple[float, ...]:
        """(ax, ay, avx, avy, ox, oy, theta, ovx, ovy, omega), read once per step."""
        snap = self._snap
        if snap is None:
            self._require()
            a, b = self._cp_agent, self._cp_body
            p, v = _cp.cpBodyGetPosition(a), _cp.cpBodyGetVelocity(a)
            q, w = _cp.cpBodyGetPosition(b), _cp.cpBodyGetVelocity(b)
            snap = self._snap = (p.x, p.y, v.x, v.y, q.x, q.y, _cp.cpBodyGetAngle(b),
                                 w.x, w.y, _cp.cpBodyGetAngularVelocity(b))
        return snap

    def get_state(self) -> SimState:
        """The current state, read from the bodies (equal to the reset state before any step)."""
        r = self._read()
        return SimState.trusted(self._state.shape, r[0:2], r[2:4], r[4:7], r[7:10], self._state.physics)

    def state_vector(self, out: np.ndarray | None = None) -> np.ndarray:
        """(11,) float64 in ``STATE_FIELDS`` order, written into ``out`` when given."""
        r = self._read()
        if out is None:
            out = np.empty(STATE_DIM)
        out[:10] = r
        out[10] = 1.0 if self.contact_gap() <= CONTACT_TOLERANCE else 0.0
        return out

    def in_contact(self) -> bool:
        """Whether pusher and object touch (gap at most ``CONTACT_TOLERANCE``)."""
        return self.contact_gap() <= CONTACT_TOLERANCE

    def contact_gap(self) -> float:
        """Distance between the pusher's rim and the object's boundary (0 or less when overlapping)."""
        ax, ay, _, _, ox, oy, theta, _, _, _ = self._read()
        c, s = math.cos(theta), math.sin(theta)
        dx, dy = ax - ox, ay - oy
        return self._geom.distance(c * dx + s * dy, -s * dx + c * dy) - AGENT_RADIUS

    def _require(self) -> None:
        if self._space is None:
            raise RuntimeError("PushSim: reset(state) must be called before stepping or reading it")

    # -- rendering -----------------------------------------------------------------------------
    def render_into(self, out: np.ndarray) -> np.ndarray:
        """Draws the current frame into ``out`` ((S, S, 3) uint8, C-contiguous) and returns it."""
        ax, ay, _, _, ox, oy, theta, _, _, _ = self._read()
        np.copyto(out, self._bg)
        k, size16 = self._k, WORLD_SIZE * self._k
        half = _ONE // 2  # pixel centres sit at integer coordinates
        c, s = math.cos(theta), math.sin(theta)
        bx, by = ox * k - half, size16 - oy * k - half
        geom: ShapeGeometry = self._geom
        if geom.rects:
            # Row vectors (lx, ly) @ rot: world rotation, scaling and the y flip in one product.
            rot = np.array(((c * k, -s * k), (-s * k, -c * k)))
            pts = np.rint(geom.outline @ rot + (bx, by)).astype(np.int32)
            cv2.fillPoly(out, (pts,), self._palette[self._state.shape], cv2.LINE_AA, _SHIFT)
        else:
            cv2.circle(out, (round(bx), round(by)), round(geom.radius * k), self._palette[self._state.shape], -1,
                       cv2.LINE_AA, _SHIFT)
            # A mark near the rim makes the disk's rotation visible.
            r = 0.6 * geom.radius * k
            cv2.circle(out, (round(bx + c * r), round(by - s * r)), round(0.22 * geom.radius * k),
                       MARKER_RGB, -1, cv2.LINE_AA, _SHIFT)
        cv2.circle(out, (round(ax * k - half), round(size16 - ay * k - half)), round(AGENT_RADIUS * k),
                   AGENT_RGB, -1, cv2.LINE_AA, _SHIFT)
        return out

    def render(self) -> np.ndarray:
        """A new (S, S, 3) uint8 RGB frame of the current state."""
        return self.render_into(np.empty((self.image_size, self.image_size, 3), np.uint8))


class PushEnv(gym.Env):
    """The pushing task as a ``gymnasium.Env``: RGB frames in, absolute pusher targets out.

    ``reset(seed=..., options={"state": SimState | dict})`` starts from that exact state;
    without one, a state is drawn with ``sample_state`` from the env's seeded generator
    (``shape=None`` draws a shape per episode). Reward is always 0: the env is a data source.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, image_size: int = 64, shape: str | None = "T",
                 physics: Mapping[str, float] | None = None, max_steps: int = 200,
                 render_mode: str | None = "rgb_array") -> None:
        if shape is not None:
            get_shape(shape)
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps: expected a positive int, found {max_steps!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected 'rgb_array' or None, found {render_mode!r}")
        self.sim = PushSim(image_size)
        self.shape = shape
        self.physics = resolve_physics(physics) if physics is not None else None
        self.max_steps = max_steps
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        self.action_space = gym.spaces.Box(0.0, WORLD_SIZE, (2,), np.float32)
        self._steps = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        state = (options or {}).get("state")
        if state is None:
            state = sample_state(self.np_random, shape=self.shape, physics=self.physics)
        elif not isinstance(state, SimState):
            state = SimState.from_dict(state)
        self.sim.reset(state)
        self._steps = 0
        return self.sim.render(), {"contact": self.sim.in_contact()}

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (2,) or not np.all(np.isfinite(a)):
            raise ValueError(f"action: expected 2 finite numbers, found {action!r}")
        self.sim.step(a[0], a[1])
        self._steps += 1
        obs = self.sim.render()
        return obs, 0.0, False, self._steps >= self.max_steps, {"contact": self.sim.in_contact()}

    def render(self) -> np.ndarray:
        return self.sim.render()

    def get_state(self) -> SimState:
        """The exact simulator state."""
        return self.sim.get_state()

    def state_vector(self) -> np.ndarray:
        """(11,) float64 in ``STATE_FIELDS`` order, contact included."""
        return self.sim.state_vector()

    def in_contact(self) -> bool:
        """Whether the pusher touches the object."""
        return self.sim.in_contact()
