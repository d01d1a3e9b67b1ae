"""The simulated world: seeded terrain, rocks, craters and albedo, and its exact ground truth.

`World.build(WorldConfig(...))` generates the rock-free ground on a height grid (1 cm by default),
turns it into a bounded-error triangle mesh (rtin.py), adds every rock as its own low-poly mesh
(rocks.py), and keeps those triangles as THE surface: cameras and the time-of-flight camera are
rendered from it and every truth query is answered on it, so the two cannot disagree. The ground
grid lies within `mesh_tolerance_m` of the ground mesh.

Obstacles no map knew (a dropped rock, a standing person: obstacles.py) can be added to a built world
and removed again. They join THE surface as a small dynamic part of it (mesh.TriangleSurface.
with_dynamic), the rock table and `heights`; the world's own state (surface, rock_of_triangle, rocks,
heights, obstacles) is one immutable record swapped by one assignment, so a reader in another thread
(a render, a truth query) sees it before or after a change, never half of one; `snapshot()` pins it
for a reader that asks several questions.

Frames: world x east, y north, z up, metres; the world is centred on the origin.
"""
from __future__ import annotations

import copy
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import albedo as albedo_model
from .config import Sun, WorldConfig
from .grid import GridSpec, bilinear, remap_bilinear
from .heap import give_back_free_heap
from .heights import TopHeights
from .lighting import in_sunlight
from .mesh import Stacked, TriangleSurface, grid_surface_parts
from .noise import DetailTexture
from .obstacles import Obstacle, astronaut_obstacle, inside_convex, rock_obstacle
from .rocks import ROCK_REACH, ROCK_TABLE_DTYPE, RockMeshes, place_rocks, rock_table
from .rtin import extract_triangles, vertex_errors
from .terrain import ground_heights

__all__ = ["World", "WorldConfig", "Sun"]

@dataclass(frozen=True)
class _Truth:
    """What the world is at one instant; replaced whole, never changed in place."""

    surface: TriangleSurface
    rock_of_triangle: np.ndarray
    rocks: np.ndarray
    built_heights: TopHeights          # the built world's, before any added obstacle
    obstacles: tuple[Obstacle, ...]

    def heights(self) -> np.ndarray:
        """The built heights with the added obstacles' patches, as a new dense grid."""
        heights = self.built_heights.dense()
        flat = heights.reshape(-1)
        for obstacle in self.obstacles:
            flat[obstacle.points] = np.maximum(flat[obstacle.points], obstacle.tops)
        return heights

    def heights_window(self, rows: slice, cols: slice) -> np.ndarray:
        """`heights()[rows, cols]`, made from the window alone."""
        heights = self.built_heights.window(rows, cols)
        width = self.built_heights.ground.shape[1]
        r0, r1, _ = rows.indices(self.built_heights.ground.shape[0])
        c0, c1, _ = cols.indices(width)
        for obstacle in self.obstacles:
            row, col = np.divmod(obstacle.points, width)
            inside = (row >= r0) & (row < r1) & (col >= c0) & (col < c1)
            row, col = row[inside] - r0, col[inside] - c0
            heights[row, col] = np.maximum(heights[row, col], obstacle.tops[inside])
        return heights


MESH_BLOCK_CELLS = 256       # RTIN root block: the largest triangle leg, 2.56 m at 1 cm cells
FILE_FORMAT = "rvs-sim-world/2"


def _streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent random streams per part, so changing the rocks never changes the terrain."""
    names = ("terrain", "rocks", "albedo", "rock_texture", "detail")
    return {name: np.random.default_rng([seed, i]) for i, name in enumerate(names)}


class World:
    """A built world: grids, rock table, truth surface, and queries on them.

    Attributes:
        config: the WorldConfig it was built from.
        sun: the current sun; set it to relight the scene (geometry does not change).
        grid: where the generation grid lies (GridSpec).
        ground: float32 heights of the rock-free ground at the grid points (the ground mesh's source).
        heights: float32 heights with rocks: where a rock stands above the ground grid, the height of
            its surface (exact, from the rock meshes), else `ground` (within mesh_tolerance_m of the
            ground mesh).
            Added obstacles count as rocks here (the maximum of their surface and what was there).
            Kept sparse (heights.py): `heights` makes the whole grid anew on each call,
            `heights_window(rows, cols)` only the part asked for.
        albedo_grid: float32 albedo of the regolith per grid point (rocks have their own, see albedo_at).
        rocks: structured array, one row per rock (see rocks.ROCK_TABLE_DTYPE): the world's own, then
            one per added obstacle in the order of `obstacles()`.
        surface: the truth triangles, ground first, then rocks, then added obstacles (TriangleSurface).
        rock_of_triangle: rock index of each surface triangle, -1 for ground.
    """

    def __init__(self, config: WorldConfig, grid: GridSpec, heights: TopHeights, albedo_grid: np.ndarray,
                 rocks: np.ndarray, surface: TriangleSurface, rock_of_triangle: np.ndarray):
        self.config = config
        self.sun = config.sun
        self.grid = grid
        self.ground, self.albedo_grid = heights.ground, albedo_grid
        self._built = _Truth(surface, rock_of_triangle, rocks, heights, ())
        self._state = self._built
        self._changing = threading.Lock()    # one change at a time; readers never wait
        self._next_id = 1
        self._frozen = False
        streams = _streams(config.seed)
        self._detail = DetailTexture(streams["detail"])
        self._rock_texture = albedo_model.RockTexture(streams["rock_texture"], config.albedo.rock_contrast)

    # ----------------------------------------------------------------------------- the state
    @property
    def surface(self) -> TriangleSurface:
        return self._state.surface

    @property
    def rock_of_triangle(self) -> np.ndarray:
        return self._state.rock_of_triangle

    @property
    def rocks(self) -> np.ndarray:
        return self._state.rocks

    @property
    def heights(self) -> np.ndarray:
        return self._state.heights()

    def heights_window(self, rows: slice, cols: slice) -> np.ndarray:
        """`heights[rows, cols]` (unit-step slices of grid-point rows and columns), made from the
        window alone."""
        return self._state.heights_window(rows, cols)

    def snapshot(self) -> World:
        """This world as it is now, for a reader asking several questions (a render): it shares every
        array and does not see later additions or removals. It cannot be changed itself."""
        frozen = copy.copy(self)   # one reference to the state is copied: atomic
        frozen._frozen = True
        return frozen

    # ----------------------------------------------------------------------------- added obstacles
    def add_rock(self, x: float, y: float, height: float = 0.2, diameter: float | None = None,
                 seed: int | None = None, keep_clear: np.ndarray | None = None) -> int:
        """Drop a rock no map knew at (x, y): its highest point `height` above the rock-free ground,
        `diameter` (default 1.5 x height) across its body, shaped like the world's own rocks (seeded by
        `seed`, default its id). Returns its id. Raises ValueError if it would reach off the terrain
        or onto `keep_clear` (a convex polygon (K, 2) in world x, y, counter-clockwise)."""
        with self._changing:
            obstacle_id = self._new_id()
            diameter = 1.5 * height if diameter is None else diameter
            if height <= 0 or diameter <= 0:
                raise ValueError(f"a rock needs a positive height and diameter, not {height:g} and {diameter:g} m")
            self._check_reach(x, y, ROCK_REACH * diameter, "the rock")
            obstacle = rock_obstacle(obstacle_id, x, y, height, diameter, obstacle_id if seed is None else seed,
                                     self.config.rocks, self.grid, self.ground)
            self._commit(self._state.obstacles + (self._placed(obstacle, keep_clear, "the rock"),))
        return obstacle_id

    def add_astronaut(self, x: float, y: float, heading: float = 0.0, height: float = 1.8, width: float = 0.5,
                      depth: float = 0.3, keep_clear: np.ndarray | None = None) -> int:
        """Stand a person at (x, y), facing `heading` (radians CCW from east): an upright body `width`
        across and `depth` deep with a head on top, `height` above the ground. Returns its id."""
        with self._changing:
            obstacle_id = self._new_id()
            obstacle = self._astronaut(obstacle_id, x, y, heading, height, width, depth)
            self._commit(self._state.obstacles + (self._placed(obstacle, keep_clear, "the astronaut"),))
        return obstacle_id

    def move_obstacle(self, obstacle_id: int, x: float, y: float, heading: float | None = None,
                      keep_clear: np.ndarray | None = None) -> None:
        """Put an added astronaut elsewhere (a walk's step), keeping its id and size."""
        with self._changing:
            old = self._obstacle(obstacle_id)
            if old.kind != "astronaut":
                raise ValueError(f"obstacle {obstacle_id} is a {old.kind}; only an astronaut moves")
            heading = old.heading if heading is None else heading
            new = self._astronaut(obstacle_id, x, y, heading, old.height, old.size["width_m"], old.size["depth_m"])
            self._commit(tuple(self._placed(new, keep_clear, "the astronaut") if o.id == obstacle_id else o
                               for o in self._state.obstacles))

    def remove_obstacle(self, obstacle_id: int) -> None:
        """Take an added obstacle away: surface, rock row and heights are as if it had never been."""
        with self._changing:
            self._obstacle(obstacle_id)
            self._commit(tuple(o for o in self._state.obstacles if o.id != obstacle_id))

    def clear_obstacles(self, kind: str | None = None) -> list[int]:
        """Take away every added obstacle (of `kind` only, if given); returns their ids."""
        with self._changing:
            gone = [o.id for o in self._state.obstacles if kind is None or o.kind == kind]
            self._commit(tuple(o for o in self._state.obstacles if o.id not in gone))
        return gone

    def obstacles(self) -> list[dict]:
        """The added obstacles, for truth records: id, kind, x, y, heading_rad, height_m, diameter_m
        (rock) or width_m and depth_m (astronaut), seed, rock (its row in `rocks`), albedo, area_m2
        (where it tops the ground) and footprint (world x, y of an outline around it)."""
        state = self._state
        first = len(state.rocks) - len(state.obstacles)
        return [o.record(first + i) for i, o in enumerate(state.obstacles)]

    def _new_id(self) -> int:
        """The id the next added obstacle gets (taken by _commit, so a refused one takes none)."""
        if self._frozen:
            raise RuntimeError("a world snapshot cannot be changed; change the world it was taken of")
        return self._next_id

    def _obstacle(self, obstacle_id: int) -> Obstacle:
        if self._frozen:
            raise RuntimeError("a world snapshot cannot be changed; change the world it was taken of")
        for obstacle in self._state.obstacles:
            if obstacle.id == obstacle_id:
                return obstacle
        there = ", ".join(str(o.id) for o in self._state.obstacles) or "none"
        raise KeyError(f"no added obstacle {obstacle_id} (there are: {there})")

    def _astronaut(self, obstacle_id: int, x, y, heading, height, width, depth) -> Obstacle:
        if not (0 < height and 0 < width and 0 < depth):
            raise ValueError(f"an astronaut needs a positive size, not {height:g} x {width:g} x {depth:g} m")
        self._check_reach(x, y, math.hypot(width, depth) / 2, "the astronaut")
        return astronaut_obstacle(obstacle_id, x, y, heading, self.grid, self.ground, height, width, depth)

    def _check_reach(self, x: float, y: float, reach: float, what: str) -> None:
        x0, x1, y0, y1 = self.bounds
        if not (x0 + reach < x < x1 - reach and y0 + reach < y < y1 - reach):
            raise ValueError(f"{what} at ({x:.3f}, {y:.3f}) would reach {reach:.3f} m from there, off the "
                             f"world: its bounds are x {x0:g}..{x1:g}, y {y0:g}..{y1:g}")

    def _placed(self, obstacle: Obstacle, keep_clear: np.ndarray | None, what: str) -> Obstacle:
        """The obstacle, if it stays off the terrain's edge and off `keep_clear`; else ValueError."""
        rows, cols = np.divmod(obstacle.points, self.grid.cols + 1)
        xy = np.column_stack([self.grid.x_of(cols), self.grid.y_of(rows)])
        x0, x1, y0, y1 = self.bounds
        if not (x0 < obstacle.footprint[:, 0].min() and obstacle.footprint[:, 0].max() < x1
                and y0 < obstacle.footprint[:, 1].min() and obstacle.footprint[:, 1].max() < y1):
            raise ValueError(f"{what} at ({obstacle.x:.3f}, {obstacle.y:.3f}) would reach off the world: its "
                             f"bounds are x {x0:g}..{x1:g}, y {y0:g}..{y1:g}")
        if keep_clear is not None and len(xy) and inside_convex(xy, np.asarray(keep_clear, np.float64)).any():
            raise ValueError(f"{what} at ({obstacle.x:.3f}, {obstacle.y:.3f}) would land on the rover")
        return obstacle

    def _commit(self, obstacles: tuple[Obstacle, ...]) -> None:
        """Make the state with these added obstacles (from the built world's, so a removal restores
        it exactly) and put it in place with one assignment."""
        built = self._built
        self._next_id = max([self._next_id - 1] + [o.id for o in obstacles]) + 1
        if not obstacles:
            self._state = built
            return
        offsets = np.cumsum([0] + [len(o.vertices) for o in obstacles[:-1]])
        first = len(built.rocks)
        surface = built.surface.with_dynamic(
            np.concatenate([o.vertices for o in obstacles]),
            np.concatenate([o.triangles + k for o, k in zip(obstacles, offsets, strict=True)]))
        rock_of_triangle = Stacked(built.rock_of_triangle, np.concatenate(
            [np.full(len(o.triangles), first + i, np.int32) for i, o in enumerate(obstacles)]))
        rocks = np.concatenate([built.rocks, np.array([o.row for o in obstacles], dtype=ROCK_TABLE_DTYPE)])
        self._state = _Truth(surface, rock_of_triangle, rocks, built.built_heights, obstacles)

    # ----------------------------------------------------------------------------- building
    @classmethod
    def build(cls, config: WorldConfig | None = None) -> World:
        """Generate a world from its config: ground, its mesh, rocks until the cover is met, albedo."""
        config = config or WorldConfig()
        rng = _streams(config.seed)
        grid = GridSpec.centred(*config.size_m, config.cell_m, MESH_BLOCK_CELLS)
        ground = ground_heights(grid, config.terrain, config.craters, rng["terrain"])
        ground_triangles = extract_triangles(vertex_errors(ground, MESH_BLOCK_CELLS), config.mesh_tolerance_m,
                                             MESH_BLOCK_CELLS)
        bodies, meshes, tops = place_rocks(ground, grid, config.rocks, rng["rocks"])
        albedo_grid = albedo_model.regolith_albedo(grid, config.albedo, rng["albedo"])
        rocks = rock_table(bodies, meshes, grid, ground, tops)
        surface, rock_of_triangle = _truth_surface(grid, ground, ground_triangles, meshes)
        world = cls(config, grid, TopHeights.of(ground, tops.points, tops.heights), albedo_grid, rocks, surface,
                    rock_of_triangle)
        del ground_triangles, bodies, meshes, tops
        give_back_free_heap()    # the build's temporaries: a few hundred MiB the allocator would keep
        return world

    # ----------------------------------------------------------------------------- save / load
    def save(self, path: str | Path) -> Path:
        """Write the world to an .npz file; `World.load` gives back an identical world."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        if self._state.obstacles:
            ids = ", ".join(str(o.id) for o in self._state.obstacles)
            raise ValueError(f"the world has added obstacles ({ids}); a world file holds the built world only: "
                             f"clear_obstacles() first, or add them again after World.load")
        built = self._built
        np.savez(path, format=np.array(FILE_FORMAT), config=np.array(self.config.model_dump_json()),
                 sun=np.array(self.sun.model_dump_json()), ground=self.ground, top_points=built.built_heights.points,
                 tops=built.built_heights.tops, albedo=self.albedo_grid, rocks=self.rocks,
                 vertices=built.surface.vertices, triangles=built.surface.triangles,
                 rock_of_triangle=built.rock_of_triangle)
        return path

    @classmethod
    def load(cls, path: str | Path) -> World:
        with np.load(Path(path), allow_pickle=False) as data:
            if str(data["format"]) != FILE_FORMAT:
                raise ValueError(f"{path}: not a {FILE_FORMAT} file (format {data['format']}): save the world "
                                 f"again with python -m drivers.sim save")
            config = WorldConfig.model_validate_json(str(data["config"]))
            grid = GridSpec.centred(*config.size_m, config.cell_m, MESH_BLOCK_CELLS)
            heights = TopHeights(data["ground"], data["top_points"], data["tops"])
            world = cls(config, grid, heights, data["albedo"], data["rocks"].astype(ROCK_TABLE_DTYPE),
                        TriangleSurface(data["vertices"], data["triangles"]), data["rock_of_triangle"])
            world.sun = Sun.model_validate_json(str(data["sun"]))
        return world

    # ----------------------------------------------------------------------------- truth queries
    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the terrain."""
        return (self.grid.x_min, self.grid.x_max, self.grid.y_min, self.grid.y_max)

    def height_at(self, x, y) -> np.ndarray:
        """Exact height of the truth surface at world (x, y) (arrays broadcast); NaN off the terrain."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        surface = self.surface
        triangle = self._triangle_under(x, y, surface)
        return surface.height_on(triangle, x.ravel(), y.ravel()).reshape(x.shape)

    def ground_height_at(self, x, y) -> np.ndarray:
        """Height of the rock-free ground at (x, y): the reference rock protrusion is measured from
        (bilinear in the ground grid, within mesh_tolerance_m of the ground mesh); NaN off the terrain."""
        return bilinear(self.ground, self.grid, x, y)

    def protrusion_at(self, x, y) -> np.ndarray:
        """How far the truth surface stands above the rock-free ground at (x, y): rock height there,
        about 0 (within mesh_tolerance_m) on bare ground."""
        return self.height_at(x, y) - self.ground_height_at(x, y)

    def rock_at(self, x, y) -> np.ndarray:
        """Index into `rocks` of the rock that is the topmost surface at (x, y); -1 for ground."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        state = self._state
        triangle = self._triangle_under(x, y, state.surface)
        return np.where(triangle >= 0, state.rock_of_triangle[np.maximum(triangle, 0)], -1).reshape(x.shape)

    def normal_at(self, x, y) -> np.ndarray:
        """Unit upward normal (..., 3) of the truth surface at (x, y); NaN off the terrain."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        surface = self.surface
        triangle = self._triangle_under(x, y, surface)
        normals = surface.face_normals[np.maximum(triangle, 0)].astype(np.float64)
        normals[triangle < 0] = np.nan
        return normals.reshape(*x.shape, 3)

    def slope_at(self, x, y, baseline: float = 0.0) -> np.ndarray:
        """Slope angle in radians at (x, y).

        baseline 0: the slope of the mesh triangle under the point (exact, very local: a rock
        facet can be steep). baseline b > 0: the slope of the plane through the heights at
        (x +- b/2, y) and (x, y +- b/2), i.e. the slope over a patch b wide, as a rover feels it.
        """
        if baseline <= 0:
            normal = self.normal_at(x, y)
            return np.arccos(np.clip(normal[..., 2], -1.0, 1.0))
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        half = baseline / 2
        dz_dx = (self.height_at(x + half, y) - self.height_at(x - half, y)) / baseline
        dz_dy = (self.height_at(x, y + half) - self.height_at(x, y - half)) / baseline
        return np.arctan(np.hypot(dz_dx, dz_dy))

    def albedo_at(self, x, y) -> np.ndarray:
        """Albedo of the topmost surface at (x, y); NaN off the terrain."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        state = self._state
        triangle = self._triangle_under(x, y, state.surface)
        z = state.surface.height_on(triangle, x.ravel(), y.ravel())
        points = np.stack([x.ravel(), y.ravel(), z], axis=1)
        rock = np.where(triangle >= 0, state.rock_of_triangle[np.maximum(triangle, 0)], -1)
        albedo = self.albedo_of(points, rock, state.rocks)
        return np.where(triangle >= 0, albedo, np.float32(np.nan)).reshape(x.shape)

    def albedo_of(self, points: np.ndarray, rock: np.ndarray, rocks: np.ndarray | None = None) -> np.ndarray:
        """Albedo (float32) at surface points (n, 3) lying on rock `rock` (-1: on the ground).

        Ground: the regolith grid interpolated, times sub-centimetre detail. Rocks: the rock's own
        albedo times a 3-D mottling. The renderer uses exactly this, so it is the albedo truth of
        every image. `rocks`: the rock table `rock` indexes (default the current one).
        """
        rocks = self.rocks if rocks is None else rocks
        albedo = np.empty(len(points), dtype=np.float32)
        on_ground = rock < 0
        x, y = points[on_ground, 0], points[on_ground, 1]
        row, col = self.grid.fractional_index(x, y)
        detail = np.exp(np.float32(self.config.albedo.detail_contrast) * self._detail(x, y))
        albedo[on_ground] = remap_bilinear(self.albedo_grid, col, row) * detail
        on_rock = ~on_ground
        albedo[on_rock] = rocks["albedo"][rock[on_rock]] * self._rock_texture(points[on_rock])
        return albedo

    def in_sunlight(self, points: np.ndarray, normals: np.ndarray, sun: Sun | None = None) -> np.ndarray:
        """True where surface points (..., 3) with normals (..., 3) see the sun (no cast shadow)."""
        return in_sunlight(self.surface, np.asarray(points, np.float64), np.asarray(normals, np.float32),
                           sun or self.sun)

    def height_map(self, cell: float, x_range: tuple[float, float], y_range: tuple[float, float]) -> np.ndarray:
        """Truth heights at the centres of a cell grid: map[iy, ix] at
        (x_range[0] + (ix + 0.5) cell, y_range[0] + (iy + 0.5) cell); row 0 is the southern edge."""
        xs, ys = _cell_centres(cell, x_range), _cell_centres(cell, y_range)
        return self.height_at(xs[None, :], ys[:, None])

    def obstacle_mask(self, step_height: float, cell: float, x_range: tuple[float, float],
                      y_range: tuple[float, float]) -> np.ndarray:
        """Cells in which a rock stands more than `step_height` above the rock-free ground.

        Definition (hazard maps are scored against it): at every generation-grid point (1 cm) the
        protrusion is the height of the topmost rock surface there minus the height of the rock-free
        ground (terrain, slope and craters) at the same point, and 0 where no rock is on top. A cell is
        an obstacle if the largest protrusion at the grid points inside it exceeds step_height.
        Cell [iy, ix] covers x_range[0] + ix*cell <= x < x_range[0] + (ix+1)*cell and likewise in y;
        row 0 is the southern edge. Cells must be at least one grid cell wide; cells off the terrain
        are False. Slopes and crater walls are not obstacles by this definition however steep: score
        them with slope_at.
        """
        if cell < self.grid.cell - 1e-12:
            raise ValueError(f"cell {cell} m is finer than the world's grid ({self.grid.cell} m)")
        state = self._state
        return self._block_max(lambda rows, cols: state.heights_window(rows, cols) - self.ground[rows, cols], cell,
                               x_range, y_range) > step_height

    def protrusion(self) -> np.ndarray:
        """Rock protrusion above the rock-free ground at every grid point (float32, 0 off rocks)."""
        return self.heights - self.ground

    def protrusion_window(self, rows: slice, cols: slice) -> np.ndarray:
        """`protrusion()[rows, cols]`, made from the window alone."""
        return self.heights_window(rows, cols) - self.ground[rows, cols]

    def rock_cover(self) -> float:
        """Measured cumulative fractional area of rocks: the share of grid points a rock tops."""
        state = self._state
        if state.obstacles:
            return float(np.count_nonzero(self.heights > self.ground)) / self.ground.size
        return state.built_heights.topped() / self.ground.size

    # ----------------------------------------------------------------------------- helpers
    def _triangle_under(self, x: np.ndarray, y: np.ndarray, surface: TriangleSurface) -> np.ndarray:
        """Topmost triangle over each point; -1 off the terrain. Rays on the terrain's very edge
        are nudged a micrometre inward, where they cannot slip past the last triangle."""
        x, y = x.ravel(), y.ravel()
        inside = self.grid.contains(x, y)
        edge = 1e-6
        triangle = surface.triangle_under(np.clip(x, self.grid.x_min + edge, self.grid.x_max - edge),
                                               np.clip(y, self.grid.y_min + edge, self.grid.y_max - edge))
        return np.where(inside, triangle, -1)

    def _block_max(self, values_of, cell: float, x_range, y_range) -> np.ndarray:
        """Max of a per-grid-point quantity over each output cell; -inf where a cell has no point."""
        nx, ny = _cell_count(cell, x_range), _cell_count(cell, y_range)
        out = np.full((ny, nx), -np.inf)
        col_idx, cols = _points_in_cells(self.grid.x_min, self.grid.cell, self.grid.cols, x_range[0], cell, nx)
        row_idx, rows = _points_in_cells(self.grid.y_min, self.grid.cell, self.grid.rows, y_range[0], cell, ny)
        if cols is None or rows is None:
            return out
        values = values_of(rows, cols)
        col_starts, col_cells = _run_starts(col_idx)
        row_starts, row_cells = _run_starts(row_idx)
        reduced = np.maximum.reduceat(np.maximum.reduceat(values, col_starts, axis=1), row_starts, axis=0)
        out[np.ix_(row_cells, col_cells)] = reduced
        return out


def _cell_count(cell: float, value_range: tuple[float, float]) -> int:
    return max(0, int(math.ceil((value_range[1] - value_range[0]) / cell - 1e-9)))


def _cell_centres(cell: float, value_range: tuple[float, float]) -> np.ndarray:
    return value_range[0] + (np.arange(_cell_count(cell, value_range)) + 0.5) * cell


def _points_in_cells(origin: float, spacing: float, cells: int, start: float, cell: float, count: int):
    """Output-cell index of each grid point that falls in [start, start + count*cell), and their slice."""
    first = max(0, int(math.ceil((start - origin) / spacing - 1e-9)))
    last = min(cells, int(math.ceil((start + count * cell - origin) / spacing - 1e-9)) - 1)
    if last < first:
        return None, None
    coords = origin + np.arange(first, last + 1) * spacing
    index = np.floor((coords - start) / cell + 1e-9).astype(np.int64)
    keep = (index >= 0) & (index < count)
    index = index[keep]
    first += int(np.argmax(keep))
    return index, slice(first, first + len(index))


def _run_starts(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each run of equal (sorted) cell indices starts, and which cell each run is."""
    starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
    return starts, index[starts]


def _truth_surface(grid: GridSpec, ground: np.ndarray, ground_triangles: np.ndarray, rock_meshes: RockMeshes):
    """One triangle set, ground mesh first and rocks after, and each triangle's rock (-1: ground)."""
    vertices, triangles = grid_surface_parts(grid, ground, ground_triangles)
    surface = TriangleSurface(np.concatenate([vertices, rock_meshes.vertices]),
                              np.concatenate([triangles.astype(np.int64), rock_meshes.triangles + len(vertices)]))
    rock_of_triangle = np.concatenate([np.full(len(triangles), -1, np.int32), rock_meshes.rock_of_triangle])
    return surface, rock_of_triangle
