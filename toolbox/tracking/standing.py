"""What stands on the ground in one cloud: the ground taken away, the rest cut into clusters.

1. The ground: the lowest point of each ground cell, opened (a grey erosion, then a dilation) with a
   window wider than anything that may stand on it (cells whose points span more height than ground
   can are left out: they are a body's side). An opening removes what is narrower than its
   window and keeps a ramp exactly, so a person or a boulder is cut off and the terrain stays.
   Cells the sensor saw no ground in (behind a person, below the view) take the nearest ground
   cell's height within `fill_reach`, and beyond that the rover's own ground plane: at close range
   the sensor looks over a person's feet and sees no ground near them at all.
2. Standing points: more than `min_above` above that ground.
3. Clusters: the standing points' occupancy on a finer grid, joined across `join_cells` cells (a
   person's legs and arms are one body), 8-connected components with at least `min_points` points.
4. The ground under each cluster: a plane fitted to the raw ground points in a ring round it (the
   opening's lowest points sit low by the sensor's noise and on a slope by the slope across its
   window: centimetres that a person's height and z would carry), the grid's where too few.
5. Seen from afar, that ring is grazing ground the sensor measures poorly (seeded scenes: 0.1-0.3 m
   off at 7-9 m), while the feet themselves face the sensor: the lowest raw points in a column round
   the legs are the ground they stand on (within 0.03 m at any range there). Near, where the ring
   is measured well, it is kept where the feet agree with it (the column's lowest points there are
   the sensor's noise tail, 2-5 cm low) or are hidden (a rock before them: the column then starts
   well above the ring).

A noisy sensor (a stereo pair: a ground point's height spreads by about 0.0025 r^2 at range r, 0.14 m
at 7.5 m, with its median within 2 cm of the truth) is told so by `noise_per_m2`. Then the ground
cell is the median of its points, not the lowest (the lowest of a spread sits 2-3 deviations low), a
cell's spread and step may be as large as the noise makes them, a point stands only once it is
clear of the noise (4 deviations: its tail is heavy), and the ground under a cluster is the ring's fit (the feet's
lowest points are the noise's tail), the feet serving only to tell that they are hidden.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from toolbox.grid import GridSpec


@dataclass(frozen=True)
class StandingParams:
    ground_cell: float = 0.2     # m: the ground's grid
    ground_window: float = 1.6   # m: wider than anything that stands (a person 0.5 m, a boulder 1.2 m)
    fill_reach: float = 2.0      # m: a cell without ground takes the nearest ground this close
    max_ground_spread: float = 0.15   # m: a ground cell's points span no more height than this (a
                                      # body's cells span its visible height)
    max_ground_step: float = 0.15     # m: ground changes this little from one cell to the next
    min_ground_cells: int = 12        # a ground patch is at least this large (0.5 m^2)
    plane_tolerance: float = 0.4      # m: ground lies within this of the rover's plane ...
    plane_slope: float = 0.15         # ... plus this per metre away (the terrain bends)
    min_above: float = 0.25      # m: a point this far above the ground stands on it
    cell: float = 0.1            # m: the clusters' occupancy grid
    min_cell_points: int = 1     # a cell with fewer standing points is not occupied (a noisy sensor's stray
                                 # ground returns above `min_above` are single points; a body fills its cells)
    join_cells: int = 1          # occupied cells this close are one cluster
    min_points: int = 25
    ring: tuple[float, float] = (0.15, 1.0)   # m: the ground ring round a cluster's outline (step 4)
    ring_points: int = 30                     # fewer ground points there: the grid's height
    feet_radius: float = 0.35    # m: the column round the legs whose lowest points are the feet (step 5)
    feet_rank: int = 3           # the feet: this lowest point of the column (one stray return is not them)
    ring_trusted_m: float = 6.0  # m: within this range of the sensor the ring's ground is measured well
    feet_agree_m: float = 0.05   # m: feet this near the trusted ring agree with it (the ring is kept)
    feet_hidden_m: float = 0.1   # m: a column whose lowest points stand this far above the ring is hidden
    noise_per_m2: float = 0.0    # 1 sigma of a ground point's height per squared metre of range (0: the
                                 # sensor's noise is small beside the thresholds above, as the SR4000's)
    stand_sigmas: float = 4.0    # a noisy sensor's point stands once this many sigmas above the ground

    def noise_at(self, range_m: np.ndarray | float) -> np.ndarray:
        """1 sigma of a ground point's height at `range_m` from the sensor."""
        return self.noise_per_m2 * np.square(range_m)

    def min_above_at(self, range_m: np.ndarray | float) -> np.ndarray:
        """How far above the ground a point at `range_m` stands: `min_above`, or clear of the noise."""
        return np.maximum(self.min_above, self.stand_sigmas * self.noise_at(range_m))


@dataclass(frozen=True)
class Plane:
    """The ground plane under the rover: z = z0 + gx (x - x0) + gy (y - y0), world frame."""

    x0: float
    y0: float
    z0: float
    gx: float = 0.0
    gy: float = 0.0

    @classmethod
    def of_rover(cls, rover_to_world: np.ndarray) -> Plane:
        """The rover frame's z = 0 plane (its wheels' contact plane), in the world."""
        normal, origin = rover_to_world[:3, 2], rover_to_world[:3, 3]
        return cls(float(origin[0]), float(origin[1]), float(origin[2]),
                   float(-normal[0] / normal[2]), float(-normal[1] / normal[2]))

    def z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.z0 + self.gx * (np.asarray(x) - self.x0) + self.gy * (np.asarray(y) - self.y0)


@dataclass(frozen=True)
class Ground:
    """The ground's height per cell of `spec` (no NaN: every cell has a value, seen or inferred)."""

    spec: GridSpec
    heights: np.ndarray          # (rows, cols) float64
    seen: np.ndarray             # (rows, cols) bool: the cell's own ground (not filled, not the plane)

    def under(self, xy: np.ndarray) -> np.ndarray:
        """The ground height under world points (N, 2+); outside the grid the nearest edge cell's."""
        row, col, _ = self.spec.cell_of(xy[:, 0], xy[:, 1])
        row = np.clip(row, 0, self.spec.rows - 1)
        col = np.clip(col, 0, self.spec.cols - 1)
        return self.heights[row, col]


@dataclass(frozen=True)
class Cluster:
    """One group of standing points: the points (N, 3, world) and the ground under them."""

    points: np.ndarray
    ground_z: float              # the ground under the cluster (median over its cells)
    ground_seen: bool            # that ground was seen near it, not inferred from the rover's plane

    @property
    def height(self) -> float:
        """Its top above the ground under it."""
        return float(self.points[:, 2].max() - self.ground_z)

    @property
    def centroid(self) -> np.ndarray:
        return self.points.mean(axis=0)


def ground_of(points: np.ndarray, plane: Plane, params: StandingParams = StandingParams(),
              margin: float = 1.0, sensor_xy: np.ndarray | None = None) -> Ground:
    """The ground under a cloud (N, 3, world) seen from `sensor_xy` (by default the plane's origin):
    see the module's step 1."""
    spec = GridSpec.covering((points[:, 0].min() - margin, points[:, 0].max() + margin),
                             (points[:, 1].min() - margin, points[:, 1].max() + margin), params.ground_cell)
    row, col, _ = spec.cell_of(points[:, 0], points[:, 1])
    lowest = np.full(spec.shape, np.inf)
    highest = np.full(spec.shape, -np.inf)
    np.minimum.at(lowest, (row, col), points[:, 2])
    np.maximum.at(highest, (row, col), points[:, 2])
    noise = _cell_noise(spec, plane, params, sensor_xy)
    spread = highest - lowest
    if params.noise_per_m2 > 0:   # a noisy sensor: the cell's median is its ground, the lowest its noise
        lowest = np.where(np.isfinite(lowest), _cell_medians(row, col, points[:, 2], spec.shape), np.inf)
    # A cell whose points stand tall is a body's side, not ground: without this, a person whose feet
    # are below the view would be its own ground.
    lowest[spread > params.max_ground_spread + np.minimum(6.0 * noise, 0.6)] = np.inf
    lowest[~_ground_patches(lowest, plane, spec, params, noise)] = np.inf
    size = max(1, int(round(params.ground_window / params.ground_cell)) | 1)
    eroded = ndimage.minimum_filter(lowest, size=size, mode="constant", cval=np.inf)
    opened = ndimage.maximum_filter(np.where(np.isfinite(eroded), eroded, -np.inf), size=size,
                                    mode="constant", cval=-np.inf)
    seen = np.isfinite(opened) & np.isfinite(lowest)
    opened = np.where(seen, np.minimum(opened, lowest), np.nan)
    xs, ys = spec.centres()
    gx, gy = np.meshgrid(xs, ys)
    heights = plane.z(gx, gy)
    if seen.any():
        distance, (near_row, near_col) = ndimage.distance_transform_edt(~seen, return_indices=True)
        reach = distance * params.ground_cell <= params.fill_reach
        heights = np.where(reach, opened[near_row, near_col], heights)
    return Ground(spec, heights, seen)


def _cell_noise(spec: GridSpec, plane: Plane, params: StandingParams, sensor_xy: np.ndarray | None) -> np.ndarray:
    """1 sigma of a ground point's height in each cell (zeros for a sensor without `noise_per_m2`)."""
    if params.noise_per_m2 <= 0:
        return np.zeros(spec.shape)
    x0, y0 = (plane.x0, plane.y0) if sensor_xy is None else (float(sensor_xy[0]), float(sensor_xy[1]))
    xs, ys = spec.centres()
    return params.noise_at(np.hypot(xs[None, :] - x0, ys[:, None] - y0))


def _cell_medians(row: np.ndarray, col: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The median height of each cell's points (NaN where it has none)."""
    flat = row.astype(np.int64) * shape[1] + col
    order = np.lexsort((z, flat))
    flat, z = flat[order], z[order]
    starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]])
    counts = np.diff(np.r_[starts, len(flat)])
    lower, upper = starts + (counts - 1) // 2, starts + counts // 2
    medians = np.full(shape[0] * shape[1], np.nan)
    medians[flat[starts]] = (z[lower] + z[upper]) / 2
    return medians.reshape(shape)


def _ground_patches(lowest: np.ndarray, plane: Plane, spec: GridSpec, params: StandingParams,
                    noise: np.ndarray | None = None) -> np.ndarray:
    """The cells that belong to ground: patches of neighbouring cells whose heights change as ground
    can (by at most `max_ground_step` from cell to cell), at least `min_ground_cells` large, lying
    where the rover's own plane says ground may lie. Flying pixels behind a silhouette and the flat
    tops of shoulders make small patches high above their surroundings; they are dropped."""
    seen = np.isfinite(lowest)
    noise = np.zeros(lowest.shape) if noise is None else noise
    index = np.full(lowest.shape, -1, dtype=np.int64)
    index[seen] = np.arange(int(seen.sum()))
    rows, cols = lowest.shape
    sources, targets = [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = (slice(0, rows - dr), slice(max(0, -dc), cols - max(0, dc)))
        b = (slice(dr, rows), slice(max(0, dc), cols - max(0, -dc) if dc < 0 else cols))
        with np.errstate(invalid="ignore"):   # inf - inf where neither is seen: not an edge either way
            step = np.abs(lowest[a] - lowest[b])
        allowed = params.max_ground_step * max(1, abs(dc) + dr) + 2.0 * np.maximum(noise[a], noise[b])
        both = seen[a] & seen[b] & (step <= allowed)
        sources.append(index[a][both])
        targets.append(index[b][both])
    count = int(seen.sum())
    if count == 0:
        return seen
    source, target = np.concatenate(sources), np.concatenate(targets)
    graph = coo_matrix((np.ones(len(source)), (source, target)), shape=(count, count))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    xs, ys = spec.centres()
    row, col = np.nonzero(seen)
    distance = np.hypot(xs[col] - plane.x0, ys[row] - plane.y0)
    near_plane = np.abs(lowest[row, col] - plane.z(xs[col], ys[row])) <= (params.plane_tolerance
                                                                         + params.plane_slope * distance)
    agrees = np.bincount(label, weights=near_plane.astype(float)) / size
    keep = (size[label] >= params.min_ground_cells) & (agrees[label] >= 0.5)
    patches = np.zeros(lowest.shape, dtype=bool)
    patches[row[keep], col[keep]] = True
    return patches


def standing_clusters(points: np.ndarray, ground: Ground, params: StandingParams = StandingParams(),
                      sensor_xy: np.ndarray | None = None) -> list[Cluster]:
    """The clusters of what stands more than `min_above` on the ground (steps 2 to 5: 5 with the
    sensor's place), largest first."""
    if len(points) == 0:
        return []
    reach = params.min_above if sensor_xy is None else params.min_above_at(
        np.hypot(points[:, 0] - sensor_xy[0], points[:, 1] - sensor_xy[1]))
    above = points[:, 2] - ground.under(points) > reach
    standing = points[above]
    if len(standing) < params.min_points:
        return []
    spec = GridSpec.covering((standing[:, 0].min(), standing[:, 0].max() + 1e-6),
                             (standing[:, 1].min(), standing[:, 1].max() + 1e-6), params.cell)
    row, col, _ = spec.cell_of(standing[:, 0], standing[:, 1])
    row, col = np.clip(row, 0, spec.rows - 1), np.clip(col, 0, spec.cols - 1)
    counts = np.zeros(spec.shape, dtype=np.int64)
    np.add.at(counts, (row, col), 1)
    occupied = counts >= params.min_cell_points
    joined = ndimage.binary_dilation(occupied, iterations=params.join_cells) if params.join_cells else occupied
    labels, count = ndimage.label(joined, structure=np.ones((3, 3), dtype=bool))
    of_point = np.where(occupied[row, col], labels[row, col], 0)   # a sparse cell's points belong to nothing
    order = np.argsort(of_point, kind="stable")
    bounds = np.searchsorted(of_point[order], np.arange(1, count + 2))
    reach_cells = max(1, int(round(params.fill_reach / ground.spec.cell)))
    seen_near = ndimage.binary_dilation(ground.seen, iterations=reach_cells)
    clusters = []
    for label in range(count):
        members = standing[order[bounds[label]:bounds[label + 1]]]
        if len(members) < params.min_points:
            continue
        under_row, under_col, _ = ground.spec.cell_of(members[:, 0], members[:, 1])
        under_row = np.clip(under_row, 0, ground.spec.rows - 1)
        under_col = np.clip(under_col, 0, ground.spec.cols - 1)
        grid_z = float(np.median(ground.heights[under_row, under_col]))
        ground_z = local_ground(points, ground, members, grid_z, params, sensor_xy)
        if sensor_xy is not None:
            ground_z = feet_ground(points, members, ground_z, sensor_xy, params)
        clusters.append(Cluster(members, ground_z, bool(seen_near[under_row, under_col].any())))
    return sorted(clusters, key=lambda c: -len(c.points))


def local_ground(points: np.ndarray, ground: Ground, members: np.ndarray, grid_z: float,
                 params: StandingParams = StandingParams(), sensor_xy: np.ndarray | None = None) -> float:
    """Step 4: the ground height at a cluster's middle from the raw points round it that are ground
    (within `min_above` of the grid's ground, or the noise's reach at its range) and lie `ring` beyond
    its outline: a least-squares plane, refitted once without the points more than three deviations off."""
    middle = np.median(members[:, :2], axis=0)
    radius = float(np.percentile(np.linalg.norm(members[:, :2] - middle, axis=1), 90))
    low, high = radius + params.ring[0], radius + params.ring[1]
    near = np.abs(points[:, 0] - middle[0]) <= high
    near &= np.abs(points[:, 1] - middle[1]) <= high
    candidates = points[near]
    distance = np.linalg.norm(candidates[:, :2] - middle, axis=1)
    ring = candidates[(distance >= low) & (distance <= high)]
    reach = params.min_above
    if sensor_xy is not None:
        reach = float(params.min_above_at(float(np.linalg.norm(middle - sensor_xy))))
    ring = ring[np.abs(ring[:, 2] - ground.under(ring)) <= reach]
    if len(ring) < params.ring_points:
        return grid_z
    design = np.column_stack([np.ones(len(ring)), ring[:, 0] - middle[0], ring[:, 1] - middle[1]])
    keep = np.ones(len(ring), dtype=bool)
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(design[keep], ring[keep, 2], rcond=None)
        residual = ring[:, 2] - design @ coef
        keep = np.abs(residual) <= 3 * max(float(np.std(residual[keep])), 0.005)
        if keep.sum() < params.ring_points:
            return grid_z
    return float(coef[0])


def feet_ground(points: np.ndarray, members: np.ndarray, ring_z: float, sensor_xy: np.ndarray,
                params: StandingParams = StandingParams()) -> float:
    """Step 5: the ground a cluster stands on from its feet (the `feet_rank` lowest raw point in a
    column round the middle of its lower part), or `ring_z` where the ring is trusted and the feet
    agree with it or are hidden."""
    lower = members[members[:, 2] <= members[:, 2].min() + 0.4 * (members[:, 2].max() - members[:, 2].min())]
    middle = np.median(lower[:, :2], axis=0)
    near = np.abs(points[:, 0] - middle[0]) <= params.feet_radius
    near &= np.abs(points[:, 1] - middle[1]) <= params.feet_radius
    column = points[near]
    column = column[np.linalg.norm(column[:, :2] - middle, axis=1) <= params.feet_radius, 2]
    if len(column) < params.feet_rank:
        return ring_z
    feet = float(np.partition(column, params.feet_rank - 1)[params.feet_rank - 1])
    range_m = float(np.linalg.norm(middle - np.asarray(sensor_xy, dtype=float)))
    if params.noise_per_m2 > 0:   # the column's lowest points are the noise's tail: the ring, unless hidden
        low = float(np.percentile(column, 10))
        hidden = low > ring_z + params.feet_hidden_m + 2.0 * float(params.noise_at(range_m))
        return feet if hidden else ring_z
    trusted = range_m <= params.ring_trusted_m
    if trusted and (abs(feet - ring_z) <= params.feet_agree_m or feet > ring_z + params.feet_hidden_m):
        return ring_z
    return feet
