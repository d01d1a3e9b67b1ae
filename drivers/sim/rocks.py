"""Rocks of the simulated world: sizes from a power law, faceted irregular shapes, partial burial.

Each rock is its own small mesh, not a bump in the height grid: meshing rocks into the 1 cm ground
grid costs thousands of triangles along every rock outline (we measured 5.3 M triangles for the
default 40 m scene that way), while a rock mesh costs 30 to 150.

A rock is a polar grid of vertices: rings at fractions of an irregular outline (an ellipse with
random harmonics), all rings sharing the same jittered sector azimuths, plus a top vertex. Vertex
heights come from a random convex roof, the minimum over a dozen planes (steep side facets, inclined
top facets, sometimes a flat top), so groups of vertices share planes and the rock shows flat faces
and edges like broken stone. A skirt ring just outside the outline reaches below the ground so the
rock meets it without a gap. Because every ring lies inside the one below it at the same azimuths,
every facet faces up: rocks are 2.5-D (no undercuts), so the topmost surface over any point is well
defined and the truth can be a height. The roof is centred (1 - 2 * buried_fraction) half-heights
above the ground at the rock's centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from .config import RockConfig
from .grid import GridSpec, bilinear
from .mesh import TriangleSurface

ROCK_TABLE_DTYPE = np.dtype([
    ("x", "f8"), ("y", "f8"),            # centre of the rock body, world metres
    ("radius", "f8"),                    # bounding radius of the exposed footprint about (x, y)
    ("area", "f8"),                      # exposed footprint area, m^2 (where the rock is the top surface)
    ("height", "f8"),                    # highest point above the rock-free ground
    ("buried_fraction", "f8"),           # share of the body's full height below the ground
    ("diameter", "f8"),                  # body major axis (the power-law variable)
    ("albedo", "f8"),                    # mean albedo of the rock's surface
])


@dataclass(frozen=True)
class RockShape:
    """Topology of one level of detail: sectors per ring and ring sizes as fractions of the outline."""

    sectors: int
    rings: tuple[float, ...]          # descending from 1.0 (the outline) toward the top

    @property
    def vertices_per_rock(self) -> int:
        return self.sectors * (len(self.rings) + 1) + 1   # + skirt ring + top

    def triangles(self) -> np.ndarray:
        """Triangles of one rock, counter-clockwise seen from above; vertices 0..n-1 are the skirt."""
        n, rings = self.sectors, len(self.rings) + 1
        j = np.arange(n)
        faces = []
        for ring in range(rings - 1):
            outer, inner = ring * n + j, (ring + 1) * n + j
            outer_next, inner_next = ring * n + (j + 1) % n, (ring + 1) * n + (j + 1) % n
            faces += [np.stack([outer, outer_next, inner_next], 1), np.stack([outer, inner_next, inner], 1)]
        last = (rings - 1) * n
        faces.append(np.stack([last + j, last + (j + 1) % n, np.full(n, rings * n)], 1))
        return np.concatenate(faces)


# Small rocks get few facets; boulders, which a camera sees large, get more. (upper diameter, shape)
ROCK_SHAPES = ((0.10, RockShape(6, (1.0, 0.55))),
               (0.30, RockShape(9, (1.0, 0.72, 0.42))),
               (math.inf, RockShape(14, (1.0, 0.82, 0.62, 0.42, 0.22))))
SIDE_FACETS, TOP_FACETS = 6, 4
SKIRT_SCALE = 1.08          # the skirt ring lies this much outside the outline: a leaning foot
OUTLINE_HARMONICS = (2, 3, 4, 5)
# The farthest a rock reaches from its centre, in diameters: outline harmonics add at most
# sum(0.25 / k) = 0.32 to the half-diameter, and the skirt 8 % more.
ROCK_REACH = 0.5 * (1 + sum(0.25 / k for k in OUTLINE_HARMONICS)) * SKIRT_SCALE


@dataclass
class RockBodies:
    """The generated rock bodies, one entry per rock (float64)."""

    x: np.ndarray
    y: np.ndarray
    diameter: np.ndarray
    aspect: np.ndarray
    height_ratio: np.ndarray
    buried_fraction: np.ndarray
    orientation: np.ndarray
    albedo: np.ndarray

    def __len__(self) -> int:
        return len(self.x)

    @staticmethod
    def concat(parts: list[RockBodies]) -> RockBodies:
        return RockBodies(**{f.name: np.concatenate([getattr(p, f.name) for p in parts])
                             for f in fields(RockBodies)})


@dataclass
class RockMeshes:
    """Triangles of a set of rocks, and which rock each triangle belongs to."""

    vertices: np.ndarray          # (V, 3) float64
    triangles: np.ndarray         # (T, 3) indices into vertices
    rock_of_triangle: np.ndarray  # (T,) int32
    rock_of_vertex: np.ndarray    # (V,) int32

    @staticmethod
    def concat(parts: list[RockMeshes], rock_offsets: list[int]) -> RockMeshes:
        vertex_offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])

        def shifted(name: str, offsets) -> np.ndarray:
            return np.concatenate([getattr(p, name) + o for p, o in zip(parts, offsets, strict=True)])
        return RockMeshes(vertices=np.concatenate([p.vertices for p in parts]),
                          triangles=shifted("triangles", vertex_offsets),
                          rock_of_triangle=shifted("rock_of_triangle", rock_offsets).astype(np.int32),
                          rock_of_vertex=shifted("rock_of_vertex", rock_offsets).astype(np.int32))


# ------------------------------------------------------------------------------------ sampling
def power_law_diameters(rng: np.random.Generator, count: int, low: float, high: float,
                        exponent: float) -> np.ndarray:
    """Diameters with N(>D) proportional to D**-exponent on [low, high] (inverse-CDF sampling)."""
    u = rng.random(count)
    return low * (1.0 - u * (1.0 - (low / high) ** exponent)) ** (-1.0 / exponent)


def sample_rock_bodies(rng: np.random.Generator, config: RockConfig, grid: GridSpec, area_m2: float) -> RockBodies:
    """Draw rocks until their nominal footprints (pi/4 D^2 * aspect) add up to `area_m2`."""
    diameters: list[np.ndarray] = []
    total = 0.0
    aspect_mean = float(np.mean(config.aspect_range))
    while total < area_m2:
        batch = power_law_diameters(rng, 1024, *config.diameter_range_m, config.size_exponent)
        cumulative = total + np.cumsum(math.pi / 4 * batch**2 * aspect_mean)
        keep = min(len(batch), int(np.searchsorted(cumulative, area_m2)) + 1)
        diameters.append(batch[:keep])
        total = float(cumulative[keep - 1])
    diameter = np.concatenate(diameters) if diameters else np.zeros(0)
    n = len(diameter)
    x, y = _centres(rng, config, grid, diameter)
    return RockBodies(x=x, y=y, diameter=diameter, aspect=rng.uniform(*config.aspect_range, n),
                      height_ratio=rng.uniform(*config.height_ratio_range, n),
                      buried_fraction=rng.uniform(*config.buried_fraction_range, n),
                      orientation=rng.uniform(0.0, 2 * math.pi, n), albedo=rng.uniform(*config.albedo_range, n))


def _centres(rng, config: RockConfig, grid: GridSpec, diameter: np.ndarray):
    """Uniform centres, redrawn while a rock would reach into the clear circle at the origin.

    Rocks also stay wholly inside the terrain, so the truth is defined wherever a rock is.
    """
    reach = ROCK_REACH * diameter
    x = rng.uniform(grid.x_min + reach, grid.x_max - reach)
    y = rng.uniform(grid.y_min + reach, grid.y_max - reach)
    for _ in range(1000):
        too_close = np.hypot(x, y) < config.clear_radius_m + reach
        if not too_close.any():
            return x, y
        x[too_close] = rng.uniform(grid.x_min + reach[too_close], grid.x_max - reach[too_close])
        y[too_close] = rng.uniform(grid.y_min + reach[too_close], grid.y_max - reach[too_close])
    raise ValueError(f"no room for rocks outside the clear radius {config.clear_radius_m} m")


# ------------------------------------------------------------------------------------ meshes
def rock_meshes(bodies: RockBodies, grid: GridSpec, ground: np.ndarray, rng: np.random.Generator) -> RockMeshes:
    """Meshes for all rocks, one level of detail per size class."""
    parts = []
    lower = 0.0
    for upper, shape in ROCK_SHAPES:
        members = np.flatnonzero((bodies.diameter >= lower) & (bodies.diameter < upper))
        lower = upper
        if len(members):
            parts.append(_rock_meshes(bodies, members, shape, grid, ground, rng))
    if not parts:
        none = np.zeros(0, np.int32)
        return RockMeshes(np.zeros((0, 3)), np.zeros((0, 3), np.int64), none, none)
    return RockMeshes.concat(parts, [0] * len(parts))


def _rock_meshes(bodies: RockBodies, rock: np.ndarray, shape: RockShape, grid: GridSpec, ground: np.ndarray,
                 rng: np.random.Generator) -> RockMeshes:
    """Meshes for the rocks `rock`, all with the same topology."""
    count, n = len(rock), shape.sectors
    a = bodies.diameter[rock] / 2
    b = a * bodies.aspect[rock]
    c = bodies.diameter[rock] * bodies.height_ratio[rock] / 2
    # Polar layout in the rock's frame, in units of the semi-axes (u = x / a, v = y / b).
    azimuth = (np.arange(n) + rng.uniform(-0.3, 0.3, (count, n))) * (2 * math.pi / n)
    outline = _outline(rng, azimuth)                                         # (count, n)
    scale = np.concatenate([[SKIRT_SCALE], shape.rings])                     # skirt, then rings
    radius = outline[:, None, :] * scale[None, :, None]                      # (count, rings, n)
    top_u, top_v = _top_offset(rng, count, shape)
    u = np.concatenate([(radius * np.cos(azimuth)[:, None, :]).reshape(count, -1), top_u], axis=1)
    v = np.concatenate([(radius * np.sin(azimuth)[:, None, :]).reshape(count, -1), top_v], axis=1)
    roof = _roof(rng, count)(u, v)                                           # in half-heights
    local = np.stack([u * a[:, None], v * b[:, None], roof * c[:, None]], axis=-1)
    world = _placed(bodies, rock, local, c, grid, ground)
    _sink_skirt(world, n, c, grid, ground)
    triangles = shape.triangles()
    faces = (triangles[None, :, :] + (np.arange(count) * shape.vertices_per_rock)[:, None, None]).reshape(-1, 3)
    return RockMeshes(vertices=world.reshape(-1, 3), triangles=faces,
                      rock_of_triangle=np.repeat(rock, len(triangles)).astype(np.int32),
                      rock_of_vertex=np.repeat(rock, shape.vertices_per_rock).astype(np.int32))


def _outline(rng: np.random.Generator, azimuth: np.ndarray) -> np.ndarray:
    """Irregular outline radius (unit ellipse = 1) at each azimuth: random low harmonics."""
    count = len(azimuth)
    radius = np.ones_like(azimuth)
    for k in OUTLINE_HARMONICS:
        amplitude = rng.uniform(0.0, 0.25 / k, (count, 1))
        radius += amplitude * np.cos(k * azimuth + rng.uniform(0, 2 * math.pi, (count, 1)))
    return radius


def _top_offset(rng: np.random.Generator, count: int, shape: RockShape):
    """The top vertex leans off centre, but stays inside the innermost ring."""
    lean = 0.4 * shape.rings[-1] * (1 - sum(0.25 / k for k in OUTLINE_HARMONICS))
    return rng.uniform(-lean, lean, (count, 1)), rng.uniform(-lean, lean, (count, 1))


def _roof(rng: np.random.Generator, count: int):
    """A random convex roof per rock: height(u, v) = min over planes tangent to a unit sphere.

    Side facets have normals 20-60 degrees above the horizon (steep faces), top facets are
    inclined, and one near-level cap sits at 65-100 % of the half-height, so some rocks are tabular.
    """
    side_jitter = rng.uniform(-0.3, 0.3, (count, SIDE_FACETS))
    side_azimuth = (np.arange(SIDE_FACETS) + side_jitter) * (2 * math.pi / SIDE_FACETS)
    side_elevation = np.radians(rng.uniform(20.0, 60.0, (count, SIDE_FACETS)))
    top_azimuth = rng.uniform(0, 2 * math.pi, (count, TOP_FACETS))
    top_elevation = np.radians(np.concatenate([rng.uniform(50.0, 78.0, (count, TOP_FACETS - 1)),
                                               rng.uniform(80.0, 90.0, (count, 1))], axis=1))
    support = np.concatenate([rng.uniform(0.85, 1.05, (count, SIDE_FACETS + TOP_FACETS - 1)),
                              rng.uniform(0.65, 1.0, (count, 1))], axis=1)
    azimuth = np.concatenate([side_azimuth, top_azimuth], axis=1)
    elevation = np.concatenate([side_elevation, top_elevation], axis=1)
    nx, ny, nz = np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)

    # A whole-rock tilt (adding a plane keeps every facet facing up) makes rocks lie askew.
    tilt_u, tilt_v = rng.uniform(-0.25, 0.25, (count, 1)), rng.uniform(-0.25, 0.25, (count, 1))

    def height(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        offset = support[:, None, :] - nx[:, None, :] * u[..., None] - ny[:, None, :] * v[..., None]
        return (offset / nz[:, None, :]).min(axis=-1) + tilt_u * u + tilt_v * v
    return height


def _placed(bodies: RockBodies, rock: np.ndarray, local: np.ndarray, c: np.ndarray, grid: GridSpec,
            ground: np.ndarray) -> np.ndarray:
    """Turn rock-frame vertices (rocks, V, 3) by each rock's orientation and move them into place."""
    ground_centre = bilinear(ground, grid, bodies.x[rock], bodies.y[rock])
    centre_z = ground_centre + c * (1.0 - 2.0 * bodies.buried_fraction[rock])
    cos_o, sin_o = np.cos(bodies.orientation[rock])[:, None], np.sin(bodies.orientation[rock])[:, None]
    world = np.empty_like(local)
    world[..., 0] = bodies.x[rock][:, None] + cos_o * local[..., 0] - sin_o * local[..., 1]
    world[..., 1] = bodies.y[rock][:, None] + sin_o * local[..., 0] + cos_o * local[..., 1]
    world[..., 2] = centre_z[:, None] + local[..., 2]
    return world


def _sink_skirt(world: np.ndarray, sectors: int, c: np.ndarray, grid: GridSpec, ground: np.ndarray) -> None:
    """Put the skirt ring below both the ground under it and the outline ring above it.

    The margin exceeds the ground mesh's tolerance, so no sliver of gap opens at the rock's foot.
    """
    skirt, outline = world[:, :sectors], world[:, sectors:2 * sectors]
    under = bilinear(ground, grid, skirt[..., 0], skirt[..., 1])
    under = np.where(np.isnan(under), outline[..., 2], under)
    margin = 0.01 + 0.05 * c[:, None]
    skirt[..., 2] = np.minimum(under, outline[..., 2]) - margin


def dropped_rock(x: float, y: float, height: float, diameter: float, rng: np.random.Generator,
                 config: RockConfig, grid: GridSpec, ground: np.ndarray) -> tuple[RockBodies, RockMeshes, int]:
    """One rock like the world's own (same shapes, roof and sunk skirt), at (x, y) with `diameter`
    and its highest point exactly `height` above the rock-free ground under that point: the body is
    drawn as the world's rocks are (aspect, height ratio, burial, orientation, albedo from `config`),
    then its heights above the ground at its centre are scaled to the protrusion asked for (a change
    of heights keeps every facet facing up, so the rock stays 2.5-D). Returns the body, the mesh and
    the number of skirt vertices (the first ones: the outermost ring, under the ground)."""
    one = lambda low_high: rng.uniform(*low_high, 1)  # noqa: E731
    bodies = RockBodies(x=np.array([float(x)]), y=np.array([float(y)]), diameter=np.array([float(diameter)]),
                        aspect=one(config.aspect_range), height_ratio=one(config.height_ratio_range),
                        buried_fraction=one(config.buried_fraction_range),
                        orientation=rng.uniform(0.0, 2 * math.pi, 1), albedo=one(config.albedo_range))
    shape = next(shape for upper, shape in ROCK_SHAPES if diameter < upper)
    mesh = _rock_meshes(bodies, np.array([0]), shape, grid, ground, rng)
    n = shape.sectors
    vertices = mesh.vertices.reshape(1, -1, 3)
    under = bilinear(ground, grid, vertices[0, :, 0], vertices[0, :, 1])
    centre = float(bilinear(ground, grid, x, y))
    body = vertices[0, n:]
    for _ in range(8):   # the highest vertex may change as the scale does; a few rounds settle it
        above = body[:, 2] - under[n:]
        top = int(np.argmax(above))
        if abs(above[top] - height) < 1e-12:
            break
        body[:, 2] = centre + (body[:, 2] - centre) * (height + under[n + top] - centre) / (body[top, 2] - centre)
    _sink_skirt(vertices, n, np.array([height / 2]), grid, ground)
    return bodies, RockMeshes(vertices[0], mesh.triangles, mesh.rock_of_triangle, mesh.rock_of_vertex), n


# ------------------------------------------------------------------------------------ footprints
def candidate_points(bodies: RockBodies, meshes: RockMeshes, grid: GridSpec) -> np.ndarray:
    """Flat indices of the grid points inside any rock's bounding box (each once)."""
    mask = np.zeros(grid.shape, dtype=bool)
    low = np.full((len(bodies), 2), np.inf)
    high = np.full((len(bodies), 2), -np.inf)
    np.minimum.at(low, meshes.rock_of_vertex, meshes.vertices[:, :2])
    np.maximum.at(high, meshes.rock_of_vertex, meshes.vertices[:, :2])
    present = np.isfinite(low[:, 0])
    col0 = np.clip(np.floor((low[present, 0] - grid.x_min) / grid.cell), 0, grid.cols + 1).astype(int)
    col1 = np.clip(np.ceil((high[present, 0] - grid.x_min) / grid.cell) + 1, 0, grid.cols + 1).astype(int)
    row0 = np.clip(np.floor((low[present, 1] - grid.y_min) / grid.cell), 0, grid.rows + 1).astype(int)
    row1 = np.clip(np.ceil((high[present, 1] - grid.y_min) / grid.cell) + 1, 0, grid.rows + 1).astype(int)
    for r0, r1, c0, c1 in zip(row0, row1, col0, col1, strict=True):
        mask[r0:r1, c0:c1] = True
    return np.flatnonzero(mask)


@dataclass
class RockTops:
    """Grid points (flat indices) where a rock is the topmost surface, its height there, which rock."""

    points: np.ndarray
    heights: np.ndarray
    rock: np.ndarray

    @staticmethod
    def highest(parts: list[RockTops]) -> RockTops:
        """Merge tops measured on separate sets of rocks: per point, the highest wins."""
        points = np.concatenate([p.points for p in parts])
        heights = np.concatenate([p.heights for p in parts])
        rock = np.concatenate([p.rock for p in parts])
        order = np.lexsort((heights, points))
        last = np.r_[points[order][1:] != points[order][:-1], True]
        keep = order[last]
        return RockTops(points[keep], heights[keep], rock[keep])


def rock_tops(surface: TriangleSurface, rock_of_triangle: np.ndarray, points: np.ndarray,
              grid: GridSpec, ground: np.ndarray) -> RockTops:
    """The grid points (flat indices) among `points` where a rock of `surface` is the topmost
    surface and stands above the ground grid."""
    rows, cols = np.divmod(points, grid.cols + 1)
    top, triangle = surface.top_height(grid.x_of(cols), grid.y_of(rows))
    rock = np.where(triangle >= 0, rock_of_triangle[np.maximum(triangle, 0)], -1)
    on_rock = (rock >= 0) & (top > ground.ravel()[points])
    return RockTops(points[on_rock], top[on_rock], rock[on_rock])


def place_rocks(ground: np.ndarray, grid: GridSpec, config: RockConfig, rng: np.random.Generator,
                rounds: int = 6) -> tuple[RockBodies, RockMeshes, RockTops]:
    """Draw rocks until the cover measured on the grid reaches config.cover.

    Each round meshes only its new rocks, finds the grid points where they stand above the ground
    grid (vertical rays from above) and sizes the next draw from the remaining deficit and the area
    gained per nominal footprint so far, which absorbs burial, facet shapes and overlaps.
    """
    target = config.cover * ground.size   # in grid points
    covered = np.zeros(ground.size, dtype=bool)
    bodies_parts, mesh_parts, top_parts, offsets = [], [], [], []
    wanted, drawn = target, 0
    for _ in range(rounds):
        if wanted <= 0:
            break
        bodies = sample_rock_bodies(rng, config, grid, wanted * grid.cell**2)
        meshes = rock_meshes(bodies, grid, ground, rng)
        tops = rock_tops(TriangleSurface(meshes.vertices, meshes.triangles), meshes.rock_of_triangle,
                         candidate_points(bodies, meshes, grid), grid, ground)
        gained = np.count_nonzero(~covered[tops.points])
        covered[tops.points] = True
        tops.rock += drawn                      # rock indices count across all rounds
        bodies_parts.append(bodies)
        mesh_parts.append(meshes)
        top_parts.append(tops)
        offsets.append(drawn)
        drawn += len(bodies)
        deficit = target - np.count_nonzero(covered)
        if deficit < 0.01 * target or gained == 0:
            break
        wanted = deficit * wanted / gained
    if not bodies_parts:
        empty = sample_rock_bodies(rng, config, grid, 0.0)
        none = np.zeros(0, np.int64)
        return empty, rock_meshes(empty, grid, ground, rng), RockTops(none, np.zeros(0), none)
    return (RockBodies.concat(bodies_parts), RockMeshes.concat(mesh_parts, offsets),
            RockTops.highest(top_parts))


def rock_table(bodies: RockBodies, meshes: RockMeshes, grid: GridSpec, ground: np.ndarray,
               tops: RockTops) -> np.ndarray:
    """One row per rock: position, exposed footprint (area, bounding radius), height above ground."""
    table = np.zeros(len(bodies), dtype=ROCK_TABLE_DTYPE)
    table["x"], table["y"], table["diameter"] = bodies.x, bodies.y, bodies.diameter
    table["buried_fraction"], table["albedo"] = bodies.buried_fraction, bodies.albedo
    table["area"] = np.bincount(tops.rock, minlength=len(bodies)) * grid.cell**2
    rows, cols = np.divmod(tops.points, grid.cols + 1)
    distance = np.hypot(grid.x_of(cols) - bodies.x[tops.rock], grid.y_of(rows) - bodies.y[tops.rock])
    radius = np.zeros(len(bodies))
    np.maximum.at(radius, tops.rock, distance + grid.cell * math.sqrt(0.5))
    table["radius"] = radius
    # The highest point of a mesh is a vertex; measure it against the ground right under it.
    under = bilinear(ground, grid, meshes.vertices[:, 0], meshes.vertices[:, 1])
    above = meshes.vertices[:, 2] - np.nan_to_num(under, nan=np.inf)
    height = np.zeros(len(bodies))
    np.maximum.at(height, meshes.rock_of_vertex, above)
    table["height"] = height
    return table
