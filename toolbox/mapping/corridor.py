"""Per-frame hazard detection along the rover's path, and a rolling memory of what the frames saw.

    view = corridor_view(points, (x, y, heading), params, direction)   # one sensor frame
    view.nearest                                   # Hit(distance, x, y, cause) or None
    memory.update(view)                            # HazardMemory: latest known state per cell
    memory.nearest((x, y, heading), direction, max_distance)

The path frame: u along the driving direction (rover x when driving forward, -x when backward), v to
its left, origin at the rover's centre. The swept corridor is the rectangle u in [-L/2, L/2 + reach],
|v| <= W/2 + side_margin (L, W: body length and width): what the footprint covers from where it
stands to `reach` past its leading edge. Distances are measured along u from the leading edge
(u = L/2); a hazard already under the footprint is at 0.

One frame is cut to the corridor grown by `context` on every side (the hazard windows need the ground
around the corridor: the step filter's ground plate is 0.5 m), gridded on a world-axis-aligned grid
aligned to multiples of the cell (so views and the memory share cells exactly, no resampling), and
run through the same chain as the maps: points_to_dem (highest point per cell), fill_small_holes,
hazard_maps. Nothing here is a new hazard rule.

Which cells are in the corridor: a cell counts when its square overlaps the swept rectangle with
positive area (the exact test for two rectangles by separating axes: the rectangle's two axes and the
world's two), so a hazard cell whose corner reaches into the corridor counts. Its distance is its
centre's, u - L/2 (0 where that is behind the leading edge): the hazard lies somewhere in the cell,
and the centre is off by at most half the square's extent along the path, (|cos| + |sin|) / 2 of a
cell (0.5 to 0.71), either way. (The square's nearest point would never be late, but is early by up
to 1.41 cells on diagonal headings; stopping margins belong to the caller.) A cell counted because
its corner reaches into the rectangle may so report a distance up to 0.71 cell past its far end.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from toolbox.grid import GridSpec
from toolbox.mapping import hazard as H
from toolbox.mapping.dem import _overlap_slices, fill_small_holes, points_to_dem

# Squares that merely touch the rectangle along an edge (overlap below this fraction of a cell) do not
# count: on axis-aligned headings the corridor's sides often fall on cell boundaries, where float
# rounding would otherwise decide.
TOUCH_TOLERANCE = 1e-6


@dataclass(frozen=True)
class CorridorParams:
    body_length: float = 0.55      # rover footprint: rover frame x forward / y left, origin at its centre
    body_width: float = 0.50
    side_margin: float = 0.10      # added each side of the swept footprint (cell size, calibration, slip)
    reach: float = 4.5             # look-ahead from the rover's leading edge, metres
    cell: float = 0.05             # the maps' cell (configs/mapping.toml cell)
    context: float = 0.6           # ground kept around the corridor for the hazard windows
    max_reach_cells: float = 2.0   # hole filling, as dem.fill_small_holes
    hazard: H.HazardConfig = field(default_factory=H.HazardConfig)

    def __post_init__(self) -> None:
        for name in ("body_length", "body_width", "cell"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("side_margin", "reach", "context", "max_reach_cells"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")

    @property
    def half_width(self) -> float:
        """Half the swept corridor's width: half the body plus the side margin."""
        return self.body_width / 2 + self.side_margin


@dataclass(frozen=True)
class Hit:
    """The nearest hazard in the path."""

    distance: float   # metres along the path from the leading edge, >= 0 (0: already under the footprint)
    x: float          # world position of the hazard cell's centre
    y: float
    cause: int        # the cell's hazard code (toolbox.mapping.hazard: HAZARD | SLOPE / STEP / ROUGHNESS)


@dataclass(frozen=True)
class Swept:
    """What the memory knows of the ground a move would sweep (HazardMemory.swept)."""

    hit: Hit | None   # the nearest remembered hazard in it (distance: from the body's edge, or the centre)
    unseen: float     # the share of its cells no frame saw
    cells: int


@dataclass(frozen=True)
class CorridorView:
    """One frame's local maps around the corridor (arrays on `spec`) and what lies in the corridor."""

    spec: GridSpec          # world-axis-aligned, aligned to multiples of the cell
    heights: np.ndarray     # float32, NaN unknown (holes filled)
    code: np.ndarray        # uint8 hazard codes (hazard.py's)
    swept: np.ndarray       # bool: cells overlapping the swept corridor
    nearest: Hit | None     # nearest hazard cell inside `swept`
    seen: float             # share of swept cells that are known (code not UNKNOWN)
    pose: tuple[float, float, float]
    direction: int


# ---------------------------------------------------------------------------------- one frame
def corridor_view(points: np.ndarray, pose: tuple[float, float, float], params: CorridorParams = CorridorParams(),
                  direction: int = 1) -> CorridorView:
    """Hazards in the corridor the footprint sweeps from `pose` (world x, y, heading in radians CCW
    from east) over `params.reach` past its leading edge, driving forward (direction +1) or backward
    (-1), from one frame's world points (N, 3; non-finite rows are ignored)."""
    _check_direction(direction)
    x0, y0, heading = (float(v) for v in pose)
    c, s = _path_axes(heading, direction)
    half_l, half_w = params.body_length / 2, params.half_width
    u_low, u_high = -half_l, half_l + params.reach
    grow = params.context

    # Keep the points in the grown corridor (a cheap mask in the path frame).
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    dx, dy = points[:, 0] - x0, points[:, 1] - y0
    u = dx * c + dy * s
    v = dy * c - dx * s
    keep = (u >= u_low - grow) & (u <= u_high + grow) & (np.abs(v) <= half_w + grow)

    spec = _covering_grid((x0, y0), (c, s), (u_low - grow, u_high + grow), half_w + grow, params.cell)
    dem = fill_small_holes(points_to_dem(points[keep], spec), params.max_reach_cells)
    code = H.hazard_maps(dem.heights, params.cell, params.hazard).code

    xs, ys = spec.centres()
    swept, distance = swept_cells(xs[None, :], ys[:, None], (x0, y0, heading), direction,
                                  params.body_length, half_w, params.reach, params.cell)
    known = swept & (code != H.UNKNOWN)
    count = int(swept.sum())
    seen = float(known.sum()) / count if count else 0.0
    rows, cols = np.nonzero(swept & H.is_hazard(code))
    nearest = _nearest_hit(spec, code, rows, cols, distance[rows, cols])
    return CorridorView(spec, dem.heights, code, swept, nearest, seen, (x0, y0, heading), direction)


def swept_cells(x: np.ndarray, y: np.ndarray, pose: tuple[float, float, float], direction: int,
                body_length: float, half_width: float, ahead: float, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(inside, distance) for world-aligned square cells of side `cell` centred at (x, y) (arrays that
    broadcast): inside where the square overlaps the rectangle u in [-L/2, L/2 + ahead], |v| <=
    half_width with positive area (separating axes: exact); distance along u from the leading edge
    (u = L/2) to the cell's centre, clipped at 0 (see the module doc)."""
    x0, y0, heading = (float(p) for p in pose)
    c, s = _path_axes(heading, direction)
    half_l = body_length / 2
    u_low, u_high = -half_l, half_l + ahead
    dx, dy = np.asarray(x, dtype=np.float64) - x0, np.asarray(y, dtype=np.float64) - y0
    u = dx * c + dy * s
    v = dy * c - dx * s
    # The square's half extent along either path axis; the rectangle's along either world axis.
    square = 0.5 * cell * (abs(c) + abs(s))
    tol = TOUCH_TOLERANCE * cell
    inside = (u > u_low - square + tol) & (u < u_high + square - tol) & (np.abs(v) < half_width + square - tol)
    # World axes: the rectangle's bounding box against the square.
    u_mid, u_half = (u_low + u_high) / 2, (u_high - u_low) / 2
    centre_x, centre_y = x0 + u_mid * c, y0 + u_mid * s
    box_x = u_half * abs(c) + half_width * abs(s) + cell / 2 - tol
    box_y = u_half * abs(s) + half_width * abs(c) + cell / 2 - tol
    inside &= (np.abs(dx + x0 - centre_x) < box_x) & (np.abs(dy + y0 - centre_y) < box_y)
    distance = np.maximum(u - half_l, 0.0)
    return inside, distance


# ---------------------------------------------------------------------------------- memory
class HazardMemory:
    """A rolling world-frame grid (`size` metres square at the view's cell, aligned to multiples of it)
    of the latest known state per cell: SAFE or a hazard code, UNKNOWN where never seen.

    update: a newer view's known cells overwrite what was there (ground seen clear again, e.g. after
    a person walked away, is clear again); its unknown cells leave the old state. When a view does
    not fit inside the grid, the grid is re-centred on the view's rover position (cell-aligned),
    keeping the cells both grids share; what falls outside is forgotten.
    nearest: the nearest remembered hazard the footprint would cover driving up to max_distance.

    One writer (update, recentre, clear: the frame activity) and any number of readers (nearest:
    the drive) may share it across threads: the grid and its placement are swapped as one reference,
    so a reader sees either grid whole; within one update a reader may see some of the view's cells
    written and others not yet, each cell old or new."""

    def __init__(self, params: CorridorParams = CorridorParams(), size: float = 16.0):
        if not size > 0:
            raise ValueError(f"size must be > 0, got {size!r}")
        self.params = params
        self.cells = max(1, int(round(size / params.cell)))
        # (placement, codes): the placement is None until the first update places the grid.
        self._grid: tuple[GridSpec | None, np.ndarray] = (None, self._blank())

    @property
    def spec(self) -> GridSpec | None:
        return self._grid[0]

    @property
    def code(self) -> np.ndarray:
        """The remembered codes on `spec` (uint8; UNKNOWN where never seen). Do not write to it."""
        return self._grid[1]

    def snapshot(self) -> tuple[GridSpec | None, np.ndarray]:
        """The placement and the codes read together (one grid, never one's placement and the other's
        codes). Do not write to the codes."""
        return self._grid

    def clear(self) -> None:
        self._grid = (None, self._blank())

    def update(self, view: CorridorView) -> None:
        if abs(view.spec.cell - self.params.cell) > 1e-9 * self.params.cell:
            raise ValueError(f"view cell {view.spec.cell} differs from the memory's {self.params.cell}")
        if self.spec is None or not self._holds(view.spec):
            self.recentre(view.pose[0], view.pose[1])
        spec, code = self._grid
        assert spec is not None   # recentred above when there was none
        target, source = _overlap_slices(view.spec, spec)
        if target is None:
            return
        new = view.code[source]
        old = code[target]
        known = new != H.UNKNOWN
        old[known] = new[known]

    def recentre(self, x: float, y: float) -> None:
        """Move the grid so its centre is the cell-aligned point nearest (x, y), keeping shared cells."""
        cell = self.params.cell
        half = self.cells / 2
        col0 = int(math.floor(x / cell - half + 0.5))
        row0 = int(math.floor(y / cell - half + 0.5))
        spec = GridSpec(col0 * cell, row0 * cell, cell, self.cells, self.cells)
        old_spec, old_code = self._grid
        if old_spec is None:
            self._grid = (spec, old_code)
            return
        code = self._blank()
        target, source = _overlap_slices(old_spec, spec)
        if target is not None:
            code[target] = old_code[source]
        self._grid = (spec, code)

    def nearest(self, pose: tuple[float, float, float], direction: int, max_distance: float) -> Hit | None:
        """The nearest remembered hazard cell the footprint would cover driving up to max_distance
        past its leading edge along its heading (direction +-1) from pose: the rectangle from the
        trailing edge to the leading edge + max_distance, half width body_width / 2 + side_margin,
        cells counted as in corridor_view. Distance from the leading edge, 0 if already under it."""
        _check_direction(direction)
        if not max_distance >= 0:
            raise ValueError(f"max_distance must be >= 0, got {max_distance!r}")
        spec, code = self._grid
        if spec is None:
            return None
        p = self.params
        x0, y0, heading = (float(v) for v in pose)
        c, s = _path_axes(heading, direction)
        half_l, half_w = p.body_length / 2, p.half_width
        # Only the cells of the rectangle's bounding box are looked at.
        window = _covering_grid((x0, y0), (c, s), (-half_l, half_l + max_distance), half_w, p.cell)
        target, _ = _overlap_slices(window, spec)
        if target is None:
            return None
        rows, cols = np.nonzero(H.is_hazard(code[target]))
        if len(rows) == 0:
            return None
        rows, cols = rows + target[0].start, cols + target[1].start
        xs, ys = spec.centre_of(rows, cols)
        inside, distance = swept_cells(xs, ys, (x0, y0, heading), direction, p.body_length, half_w,
                                       max_distance, p.cell)
        return _nearest_hit(spec, code, rows[inside], cols[inside], distance[inside])

    def swept(self, pose: tuple[float, float, float], turn: float, distance: float) -> Swept:
        """What the memory knows of the ground a move would sweep outside the footprint it stands on:
        a turn on the spot (turn != 0) the disc its corners reach (radius: the half diagonal of the
        body with its side margins); a drive (distance, negative backward) the footprint's rectangle
        beyond its leading (or trailing) edge. Cells beyond the memory's grid count as unseen."""
        p = self.params
        x0, y0, heading = (float(v) for v in pose)
        half_l, half_w = p.body_length / 2, p.half_width
        if turn:
            reach = math.hypot(half_l, half_w)
            box = GridSpec.covering((x0 - reach, x0 + reach), (y0 - reach, y0 + reach), p.cell)
        else:
            direction = 1 if distance >= 0 else -1
            box = _covering_grid((x0, y0), _path_axes(heading, direction), (-half_l, half_l + abs(distance)),
                                 half_w, p.cell)
        box = _on_lattice(box, p.cell)
        rows, cols = np.mgrid[0:box.rows, 0:box.cols]
        xs, ys = box.centre_of(rows.ravel(), cols.ravel())
        c, s = math.cos(heading), math.sin(heading)
        u, v = (xs - x0) * c + (ys - y0) * s, (ys - y0) * c - (xs - x0) * s
        body = (np.abs(u) <= half_l) & (np.abs(v) <= p.body_width / 2)       # where it stands now
        if turn:
            inside = (np.hypot(xs - x0, ys - y0) <= reach) & ~body
            along = np.hypot(xs - x0, ys - y0)
        else:
            forward = u * (1 if distance >= 0 else -1)
            inside = (forward > half_l) & (forward <= half_l + abs(distance)) & (np.abs(v) <= half_w)
            along = forward - half_l
        xs, ys, along = xs[inside], ys[inside], along[inside]
        spec, code = self._grid
        codes = np.full(len(xs), H.UNKNOWN, dtype=np.uint8)
        if spec is not None:
            row, col, known = spec.cell_of(xs, ys)
            codes[known] = code[row[known], col[known]]
        hazard = H.is_hazard(codes)
        hit = None
        if hazard.any():
            i = int(np.flatnonzero(hazard)[np.argmin(along[hazard])])
            hit = Hit(float(along[i]), float(xs[i]), float(ys[i]), int(codes[i]))
        unseen = float(np.mean(codes == H.UNKNOWN)) if len(codes) else 0.0
        return Swept(hit, unseen, len(codes))

    def _blank(self) -> np.ndarray:
        return np.full((self.cells, self.cells), H.UNKNOWN, dtype=np.uint8)

    def _holds(self, spec: GridSpec) -> bool:
        own = self.spec
        assert own is not None   # asked only once the memory has a grid
        tol = 1e-6 * own.cell
        return (spec.x_range[0] >= own.x_range[0] - tol and spec.x_range[1] <= own.x_range[1] + tol
                and spec.y_range[0] >= own.y_range[0] - tol and spec.y_range[1] <= own.y_range[1] + tol)


# ---------------------------------------------------------------------------------- helpers
def _check_direction(direction: int) -> None:
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 (forward) or -1 (backward), got {direction!r}")


def _path_axes(heading: float, direction: int) -> tuple[float, float]:
    """(cos, sin) of the driving direction in the world."""
    return direction * math.cos(heading), direction * math.sin(heading)


def _covering_grid(origin: tuple[float, float], axes: tuple[float, float], u_range: tuple[float, float],
                   half_width: float, cell: float) -> GridSpec:
    """The cell-aligned world grid covering the path-frame rectangle u in u_range, |v| <= half_width."""
    (x0, y0), (c, s) = origin, axes
    u = np.array([u_range[0], u_range[0], u_range[1], u_range[1]])
    v = np.array([-half_width, half_width, -half_width, half_width])
    xs, ys = x0 + u * c - v * s, y0 + u * s + v * c
    return GridSpec.covering((xs.min(), xs.max()), (ys.min(), ys.max()), cell)


def _on_lattice(spec: GridSpec, cell: float) -> GridSpec:
    """The grid moved onto the world's cell lattice (origin a multiple of the cell), one cell larger."""
    col0, row0 = math.floor(spec.origin_x / cell), math.floor(spec.origin_y / cell)
    return GridSpec(col0 * cell, row0 * cell, cell, spec.rows + 1, spec.cols + 1)


def _nearest_hit(spec: GridSpec, code: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                 distance: np.ndarray) -> Hit | None:
    if len(rows) == 0:
        return None
    i = int(np.argmin(distance))
    # The centre from the cell's index in the world's cell lattice, so every grid names it alike.
    col = round(spec.origin_x / spec.cell) + int(cols[i])
    row = round(spec.origin_y / spec.cell) + int(rows[i])
    x, y = (col + 0.5) * spec.cell, (row + 0.5) * spec.cell
    return Hit(float(distance[i]), float(x), float(y), int(code[rows[i], cols[i]]))
