"""Obstacles added to a built world that no map knew: a dropped rock, a standing person.

Each is a small mesh of its own (kept apart from the world's static triangles, see
mesh.TriangleSurface.with_dynamic), one row of the rock table (so albedo and rendering treat it as
the world's rocks are treated) and the grid points where it tops the rock-free ground with its height
there (the patch World.heights takes the maximum with, and drops again on removal).

The person is a suited figure of upright boxes facing its heading: two legs apart, a torso, two arms
hanging at its sides, a backpack (the life-support pack) and a helmet, its feet sunk a few
centimetres into the ground. Every box has flat tops and vertical walls, so the truth over any
point is the topmost of them (the torso over the gap between the legs) and stays a height.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import RockConfig
from .grid import GridSpec, bilinear
from .mesh import TriangleSurface
from .rocks import ROCK_TABLE_DTYPE, candidate_points, dropped_rock, rock_table, rock_tops

PERSON_ALBEDO = 0.7          # a white suit
# The suit's parts for a figure 1.8 m tall, 0.5 m across the arms and 0.3 m deep (the torso and arms;
# the backpack adds to that behind): (across, along the heading, left of the centre, ahead of it,
# bottom, top), lengths in metres at that size, heights as shares of the figure's height. A figure of
# another size scales across by width / 0.5, along by depth / 0.3.
PERSON_PARTS = (
    (0.15, 0.20, +0.10, 0.0, 0.00, 0.48),     # left leg
    (0.15, 0.20, -0.10, 0.0, 0.00, 0.48),     # right leg
    (0.36, 0.26, 0.00, 0.0, 0.46, 0.80),      # torso, hips to shoulders
    (0.07, 0.12, +0.215, 0.0, 0.44, 0.79),    # left arm
    (0.07, 0.12, -0.215, 0.0, 0.44, 0.79),    # right arm
    (0.32, 0.14, 0.00, -0.20, 0.52, 0.82),    # backpack
    (0.26, 0.28, 0.00, 0.0, 0.80, 1.00),      # helmet
)
PERSON_SIZE = (0.5, 0.3)     # the across and along the parts above are drawn for
SINK_M = 0.03                 # how far a person's base reaches below the lowest ground under it


@dataclass(frozen=True)
class Obstacle:
    """One added obstacle: what it is, where, its mesh (world frame) and its patch of the heights."""

    id: int
    kind: str                    # "rock" | "astronaut"
    x: float
    y: float
    heading: float               # radians CCW from east (a rock: its orientation)
    height: float                # rock: its highest point above the rock-free ground under that point;
                                 # astronaut: its top above the ground at (x, y)
    size: dict                   # rock: diameter_m; astronaut: width_m, depth_m
    seed: int | None
    vertices: np.ndarray         # (V, 3) float64, world
    triangles: np.ndarray        # (T, 3) indices into vertices
    footprint: np.ndarray        # (K, 2) world x, y: an outline that holds everything above the ground
    points: np.ndarray           # flat grid-point indices where it tops the rock-free ground
    tops: np.ndarray             # (len(points),) float32, its surface height there
    row: np.ndarray              # one ROCK_TABLE_DTYPE row

    def record(self, rock: int) -> dict:
        """The obstacle as the truth records it (JSON-ready); `rock` its index in World.rocks."""
        return {"id": self.id, "kind": self.kind, "x": self.x, "y": self.y, "heading_rad": self.heading,
                "height_m": self.height, **self.size, "seed": self.seed, "rock": rock,
                "albedo": float(self.row["albedo"]), "area_m2": float(self.row["area"]),
                "footprint": [[float(px), float(py)] for px, py in self.footprint]}


def rock_obstacle(obstacle_id: int, x: float, y: float, height: float, diameter: float, seed: int,
                  config: RockConfig, grid: GridSpec, ground: np.ndarray) -> Obstacle:
    rng = np.random.default_rng([seed, 2024])
    bodies, mesh, skirt = dropped_rock(x, y, height, diameter, rng, config, grid, ground)
    tops = rock_tops(TriangleSurface(mesh.vertices, mesh.triangles), mesh.rock_of_triangle,
                     candidate_points(bodies, mesh, grid), grid, ground)
    row = rock_table(bodies, mesh, grid, ground, tops)[0]
    return Obstacle(obstacle_id, "rock", float(x), float(y), float(bodies.orientation[0]), float(row["height"]),
                    {"diameter_m": float(diameter)}, int(seed), mesh.vertices, mesh.triangles.astype(np.int64),
                    mesh.vertices[:skirt, :2].copy(), tops.points, tops.heights.astype(np.float32), row)


def astronaut_obstacle(obstacle_id: int, x: float, y: float, heading: float, grid: GridSpec, ground: np.ndarray,
                       height: float = 1.8, width: float = 0.5, depth: float = 0.3) -> Obstacle:
    """A suited person standing at (x, y), facing `heading`, `height` above the ground at (x, y)."""
    cos_h, sin_h = math.cos(heading), math.sin(heading)
    scale_across, scale_along = width / PERSON_SIZE[0], depth / PERSON_SIZE[1]

    def rectangle(across: float, along: float, left: float = 0.0, ahead: float = 0.0) -> np.ndarray:
        """Corners (4, 2) counter-clockwise from above of a rectangle centred `left` and `ahead` of (x, y)."""
        local = np.array([[along, -across], [along, across], [-along, across], [-along, -across]]) / 2
        local = (local + [ahead, left]) * [scale_along, scale_across]
        return np.array([x, y]) + local @ np.array([[cos_h, sin_h], [-sin_h, cos_h]])

    parts = [(rectangle(*part[:4]), part[4], part[5]) for part in PERSON_PARTS]
    corners = np.concatenate([corners for corners, _, _ in parts])
    lo_along = min(p[3] - p[1] / 2 for p in PERSON_PARTS)
    hi_along = max(p[3] + p[1] / 2 for p in PERSON_PARTS)
    half_across = max(abs(p[2]) + p[0] / 2 for p in PERSON_PARTS)
    outline = rectangle(2 * half_across, hi_along - lo_along, 0.0, (hi_along + lo_along) / 2)
    centre = float(bilinear(ground, grid, x, y))
    feet = np.concatenate([corners[:8], [[x, y]]])
    base = float(np.nanmin(bilinear(ground, grid, feet[:, 0], feet[:, 1]))) - SINK_M
    boxes = [_upright_box(c, base if bottom == 0 else centre + bottom * height, centre + top * height)
             for c, bottom, top in parts]
    vertices = np.concatenate([v for v, _ in boxes])
    triangles = np.concatenate([t + 8 * i for i, (_, t) in enumerate(boxes)])
    surface = TriangleSurface(vertices, triangles)
    rows, cols = _box_points(grid, outline)
    points = rows * (grid.cols + 1) + cols
    height_there, triangle = surface.top_height(grid.x_of(cols), grid.y_of(rows))
    above = (triangle >= 0) & (height_there > ground.ravel()[points])
    points, tops = points[above], height_there[above]
    row = np.zeros(1, dtype=ROCK_TABLE_DTYPE)[0]
    row["x"], row["y"], row["diameter"], row["albedo"] = x, y, width, PERSON_ALBEDO
    row["area"] = len(points) * grid.cell ** 2
    row["radius"] = float(np.max(np.hypot(outline[:, 0] - x, outline[:, 1] - y)))
    under = bilinear(ground, grid, vertices[:, 0], vertices[:, 1])
    row["height"] = float(np.nanmax(vertices[:, 2] - under))
    return Obstacle(obstacle_id, "astronaut", float(x), float(y), float(heading), float(height),
                    {"width_m": float(width), "depth_m": float(depth)}, None, vertices, triangles.astype(np.int64),
                    outline, points, tops.astype(np.float32), row)


# Each side of a box: two triangles from the bottom ring (0-3) to the top ring (4-7), outward.
_BOX_TRIANGLES = np.array([t for i in range(4)
                           for t in ((i, (i + 1) % 4, (i + 1) % 4 + 4), (i, (i + 1) % 4 + 4, i + 4))]
                          + [(4, 5, 6), (4, 6, 7), (0, 2, 1), (0, 3, 2)], dtype=np.int64)


def _upright_box(corners: np.ndarray, bottom: float, top: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward triangles (12, 3) of a box on `corners` (4, 2, counter-clockwise)."""
    vertices = np.concatenate([np.column_stack([corners, np.full(4, z)]) for z in (bottom, top)])
    return vertices, _BOX_TRIANGLES


def _box_points(grid: GridSpec, polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the grid points in the bounding box of `polygon`."""
    lo, hi = polygon.min(axis=0), polygon.max(axis=0)
    cols = np.arange(max(0, math.floor((lo[0] - grid.x_min) / grid.cell)),
                     min(grid.cols, math.ceil((hi[0] - grid.x_min) / grid.cell)) + 1)
    rows = np.arange(max(0, math.floor((lo[1] - grid.y_min) / grid.cell)),
                     min(grid.rows, math.ceil((hi[1] - grid.y_min) / grid.cell)) + 1)
    r, c = np.meshgrid(rows, cols, indexing="ij")
    return r.ravel(), c.ravel()


def inside_convex(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """True for points (N, 2) inside or on a convex polygon (K, 2) given counter-clockwise."""
    inside = np.ones(len(points), dtype=bool)
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        edge = b - a
        inside &= edge[0] * (points[:, 1] - a[1]) - edge[1] * (points[:, 0] - a[0]) >= 0
    return inside
