"""Geometry of the pushed objects: T, box, L and disk.

Every shape is given in its body frame with the centre of mass at the origin,
so an object's pose (x, y, theta) is the pose of its centre of mass. The
polygon shapes are unions of axis-aligned rectangles (convex parts for the
physics, one outline polygon for drawing); the disk is a circle. Sizes are in
world units (the table is 512 x 512) and close to PushT's T in area.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from orchestrator.protocol import SHAPES

#: Radius of the disk pusher (world units), as in PushT.
AGENT_RADIUS = 15.0


@dataclass(frozen=True)
class ShapeGeometry:
    """One object shape in its body frame (centre of mass at the origin)."""

    name: str
    """Shape id, one of ``orchestrator.protocol.SHAPES``."""
    rects: tuple[tuple[float, float, float, float], ...]
    """Convex parts as (cx, cy, half_width, half_height); empty for the disk."""
    outline: np.ndarray
    """Boundary polygon (N, 2) float64 for drawing; empty (0, 2) for the disk."""
    radius: float
    """Disk radius; 0 for polygon shapes."""
    area: float
    """Area in square world units."""
    moment_per_mass: float
    """Moment of inertia about the centre of mass for unit mass."""
    friction_radius: float
    """Mean distance of the area from the centre of mass: ground torque = force x this."""
    bounding_radius: float
    """Largest distance from the centre of mass to the boundary."""

    def parts(self) -> list[np.ndarray]:
        """Convex parts as (4, 2) counter-clockwise vertex arrays (empty for the disk)."""
        return [_rect_vertices(*r) for r in self.rects]

    def distance(self, x: float, y: float) -> float:
        """Distance from the body-frame point (x, y) to the shape; 0 inside it."""
        if not self.rects:
            return max(math.hypot(x, y) - self.radius, 0.0)
        best = math.inf
        for cx, cy, hw, hh in self.rects:
            dx = abs(x - cx) - hw
            dy = abs(y - cy) - hh
            d = math.hypot(dx if dx > 0.0 else 0.0, dy if dy > 0.0 else 0.0)
            if d < best:
                best = d
        return best


def _rect_vertices(cx: float, cy: float, hw: float, hh: float) -> np.ndarray:
    return np.array([(cx - hw, cy - hh), (cx + hw, cy - hh), (cx + hw, cy + hh), (cx - hw, cy + hh)])


def _from_boxes(name: str, boxes: list[tuple[float, float, float, float]], outline: list) -> ShapeGeometry:
    """Builds a polygon shape from boxes (x0, y0, x1, y1) and its outline, re-centred on the centroid."""
    areas = np.array([(x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in boxes])
    centres = np.array([((x0 + x1) / 2, (y0 + y1) / 2) for x0, y0, x1, y1 in boxes])
    centroid = (areas[:, None] * centres).sum(0) / areas.sum()
    rects = tuple(
        (float(c[0] - centroid[0]), float(c[1] - centroid[1]), (x1 - x0) / 2, (y1 - y0) / 2)
        for c, (x0, y0, x1, y1) in zip(centres, boxes)
    )
    outline_arr = np.asarray(outline, dtype=np.float64) - centroid
    # Parallel-axis theorem per rectangle, mass shared in proportion to area.
    total = areas.sum()
    moment = sum(
        (a / total) * ((4 * hw * hw + 4 * hh * hh) / 12 + cx * cx + cy * cy)
        for a, (cx, cy, hw, hh) in zip(areas, rects)
    )
    return ShapeGeometry(
        name=name, rects=rects, outline=outline_arr, radius=0.0, area=float(total),
        moment_per_mass=float(moment), friction_radius=_mean_distance(rects),
        bounding_radius=float(np.linalg.norm(outline_arr, axis=1).max()),
    )


def _mean_distance(rects: tuple[tuple[float, float, float, float], ...], n: int = 64) -> float:
    """Area-weighted mean distance from the origin, by midpoint sampling of each rectangle."""
    total, weight = 0.0, 0.0
    for cx, cy, hw, hh in rects:
        u = (np.arange(n) + 0.5) / n * 2 - 1
        xs, ys = np.meshgrid(cx + u * hw, cy + u * hh)
        a = 4 * hw * hh
        total += a * float(np.hypot(xs, ys).mean())
        weight += a
    return total / weight


def _disk(radius: float) -> ShapeGeometry:
    return ShapeGeometry(
        name="disk", rects=(), outline=np.zeros((0, 2)), radius=radius, area=math.pi * radius**2,
        moment_per_mass=radius**2 / 2, friction_radius=2 * radius / 3, bounding_radius=radius,
    )


# PushT's T: a 120 x 30 bar on a 30 x 90 stem. Box and disk have about the same area; the L is
# a 30 x 120 upright with a 60 x 30 foot.
_GEOMETRY: dict[str, ShapeGeometry] = {
    "T": _from_boxes(
        "T", [(-60, 0, 60, 30), (-15, -90, 15, 0)],
        [(-60, 0), (-15, 0), (-15, -90), (15, -90), (15, 0), (60, 0), (60, 30), (-60, 30)],
    ),
    "box": _from_boxes("box", [(-40, -40, 40, 40)], [(-40, -40), (40, -40), (40, 40), (-40, 40)]),
    "L": _from_boxes(
        "L", [(0, 0, 30, 120), (30, 0, 90, 30)],
        [(0, 0), (90, 0), (90, 30), (30, 30), (30, 120), (0, 120)],
    ),
    "disk": _disk(45.0),
}
if tuple(_GEOMETRY) != SHAPES:
    raise RuntimeError(f"shapes.py defines {list(_GEOMETRY)} but protocol.SHAPES is {list(SHAPES)}")


def get_shape(name: str) -> ShapeGeometry:
    """The geometry of shape ``name``; raises ValueError for an unknown shape."""
    try:
        return _GEOMETRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"shape must be one of {list(SHAPES)}, found {name!r}") from None
