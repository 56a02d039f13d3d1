"""The wire contract between orchestrator, workers and operators.

A leaf module: it imports nothing else of ours, so workers on any host can
depend on it without pulling in the service.

Section 1 (this header) is the task space: what a collection request may ask
for. Both the uniform planner (which samples it) and the simulator (which
builds worlds from it) read these constants, so they cannot drift apart.
"""

from __future__ import annotations

#: Side of the square table in world units; y points up, origin bottom-left.
WORLD_SIZE = 512.0
#: Thickness of the walls along the table's border (inside WORLD_SIZE).
WALL = 8.0
#: Task families a worker may declare. One for now.
TASKS: tuple[str, ...] = ("push",)
#: Object shapes of the push task.
SHAPES: tuple[str, ...] = ("T", "box", "L", "disk")
#: Where start states are drawn from: object centre and agent position (world units).
OBJECT_RANGE = (128.0, 384.0)
AGENT_RANGE = (40.0, 472.0)
#: Physics parameters, each (low, high, default). Out-of-range values are refused.
PHYSICS_RANGES: dict[str, tuple[float, float, float]] = {
    "mass": (0.2, 5.0, 1.0),
    "friction": (0.05, 1.5, 0.6),
    "ground_friction": (0.05, 3.0, 1.0),
}
#: Collection policies a request may name.
POLICIES: tuple[str, ...] = ("random_waypoints", "push")
#: Hard caps used by validation.
MAX_EPISODE_STEPS = 1000
MAX_PREFIX_STEPS = 1000
