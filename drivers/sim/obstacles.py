"""Obstacles added to a built world that no map knew: a dropped rock, a standing person.

Each is a small mesh of its own (kept apart from the world's static triangles, see
mesh.TriangleSurface.with_dynamic), one row of the rock table (so albedo and rendering treat it as
the world's rocks are treated) and the grid points where it tops the rock-free ground with its height
there (the patch World.heights takes the maximum with, and drops again on removal).

The person is two stacked upright prisms with flat tops (body to the shoulders, then the head and
helmet), facing its heading, its base sunk a few centimetres into the ground: 2.5-D like the rocks
(every face faces up or is a vertical wall), so the truth over any point stays a height.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import RockConfig
from .grid import GridSpec, bilinear
from .mesh import TriangleSurface
from .rocks import ROCK_TABLE_DTYPE, RockShape, candidate_points, dropped_rock, rock_table, rock_tops

PERSON_ALBEDO = 0.7          # a white suit
PERSON_SHOULDER_RATIO = 0.84  # shoulders at this share of the height; the head prism above
PERSON_HEAD = (0.26, 0.24)    # head and helmet: (across, along the heading), metres
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
    """A person standing at (x, y), facing `heading`, `height` above the ground at (x, y)."""
    cos_h, sin_h = math.cos(heading), math.sin(heading)

    def rectangle(across: float, along: float) -> np.ndarray:
        """Corners (4, 2) counter-clockwise from above: along = the heading, across = to its left."""
        local = np.array([[along, -across], [along, across], [-along, across], [-along, -across]]) / 2
        return np.array([x, y]) + local @ np.array([[cos_h, sin_h], [-sin_h, cos_h]])

    body, head = rectangle(width, depth), rectangle(*PERSON_HEAD)
    centre = float(bilinear(ground, grid, x, y))
    samples = np.concatenate([body, [[x, y]], (body + [x, y]) / 2])
    base = float(np.nanmin(bilinear(ground, grid, samples[:, 0], samples[:, 1]))) - SINK_M
    shoulder, top = centre + PERSON_SHOULDER_RATIO * height, centre + height
    rings = [(body, base), (body, shoulder), (head, shoulder), (head, top)]
    vertices = np.concatenate([np.column_stack([xy, np.full(4, z)]) for xy, z in rings])
    strips = RockShape(4, (1.0, 1.0, 1.0)).triangles()[:-4]      # ring to ring, counter-clockwise outside
    last = 12
    triangles = np.concatenate([strips, [[last, last + 1, last + 2], [last, last + 2, last + 3]]])
    surface = TriangleSurface(vertices, triangles)
    rows, cols = _box_points(grid, body)
    points = rows * (grid.cols + 1) + cols
    height_there, triangle = surface.top_height(grid.x_of(cols), grid.y_of(rows))
    above = (triangle >= 0) & (height_there > ground.ravel()[points])
    points, tops = points[above], height_there[above]
    row = np.zeros(1, dtype=ROCK_TABLE_DTYPE)[0]
    row["x"], row["y"], row["diameter"], row["albedo"] = x, y, width, PERSON_ALBEDO
    row["area"] = len(points) * grid.cell ** 2
    row["radius"] = math.hypot(width, depth) / 2
    under = bilinear(ground, grid, vertices[:, 0], vertices[:, 1])
    row["height"] = float(np.nanmax(vertices[:, 2] - under))
    return Obstacle(obstacle_id, "astronaut", float(x), float(y), float(heading), float(height),
                    {"width_m": float(width), "depth_m": float(depth)}, None, vertices, triangles.astype(np.int64),
                    body, points, tops.astype(np.float32), row)


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
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0)):
        edge = b - a
        inside &= edge[0] * (points[:, 1] - a[1]) - edge[1] * (points[:, 0] - a[0]) >= 0
    return inside
