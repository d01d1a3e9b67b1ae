"""The horizontal shift between two clouds of the same ground, by matching their height maps.

ICP only descends from where it starts: on ground with little relief its cost is nearly flat for
tens of centimetres, and it stops wherever its shrinking correspondence distance leaves it (a hop
pair of the chain test: the true shift 19 cm, ICP 1 cm, with every one of its checks passed). An
exhaustive search over the shifts ICP could have to cover costs little on a height grid and sees the
whole cost surface, so it answers two questions: where the best shift is, and whether the ground
shows it at all. The shift is observable when every shift farther than `distinct` from the best fits
clearly worse (the contrast); flat ground fits every shift alike and is reported as such, not
guessed.

Heights are compared after removing their median difference: the vertical offset is ICP's to find,
and a wrong one must not favour a shift.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolbox.grid import GridSpec


@dataclass(frozen=True)
class HeightMatch:
    shift: np.ndarray       # (2,) x, y shift that moves the source onto the target, m (sub-cell)
    vertical: float         # z shift that then moves it onto the target: the median height difference, m
    misfit: float           # RMS height difference there (median difference removed), m
    runner_up: float        # the lowest misfit farther than `distinct` from the best shift, m (inf: none)
    distinct: float         # m
    overlap: int            # cells compared at the best shift
    offsets: np.ndarray     # (K,) shifts tried along each axis, m
    costs: np.ndarray       # (K, K) misfit per shift [y, x], NaN where the overlap was too small

    @property
    def contrast(self) -> float:
        """runner_up / misfit: 1 on featureless ground, larger the more the terrain pins the shift."""
        return self.runner_up / max(self.misfit, 1e-9)


def height_grid(points: np.ndarray, spec: GridSpec) -> np.ndarray:
    """Mean height per cell of the grid (rows northwards); NaN where empty."""
    points = np.asarray(points, dtype=np.float64)
    row, col, inside = spec.cell_of(points[:, 0], points[:, 1])
    flat = (row * spec.cols + col)[inside]
    total = np.bincount(flat, weights=points[inside, 2], minlength=spec.rows * spec.cols)
    count = np.bincount(flat, minlength=spec.rows * spec.cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).reshape(spec.shape)


def match_height_maps(source: np.ndarray, target: np.ndarray, centre: np.ndarray, radius: float, search: float,
                      cell: float, distinct: float, min_overlap: float = 0.5) -> HeightMatch:
    """Try every shift of `source` within +-search (a whole number of cells per axis) against `target`,
    both seen within the square of half-size radius around centre (x, y); a shift counts when the
    cells both maps fill number at least min_overlap of the most any shift shares (a shift that pushes
    the clouds apart fits a few cells by chance)."""
    if not (cell > 0 and radius >= 2 * cell and search >= 0 and distinct > 0):
        raise ValueError(f"need cell > 0, radius >= 2 cells, search >= 0, distinct > 0; got cell={cell}, "
                         f"radius={radius}, search={search}, distinct={distinct}")
    steps, cells = int(round(search / cell)), int(round(2 * radius / cell))
    corner = np.asarray(centre, dtype=np.float64)[:2] - cells * cell / 2
    fixed = height_grid(target, GridSpec(corner[0], corner[1], cell, cells, cells))
    # The source on a grid `steps` cells wider each side: each shift is a window of it.
    wider = cells + 2 * steps
    moving = height_grid(source, GridSpec(corner[0] - steps * cell, corner[1] - steps * cell, cell, wider, wider))
    filled = np.isfinite(fixed)
    if filled.sum() < 10:
        raise ValueError(f"the target has {int(filled.sum())} filled cells within {radius:g} m: too few to match")
    offsets = np.arange(-steps, steps + 1) * cell
    windows = {}
    for row, dy in enumerate(range(-steps, steps + 1)):
        for col, dx in enumerate(range(-steps, steps + 1)):
            # Moving the source by (dx, dy) cells puts its cell (y - dy, x - dx) over the target's (y, x).
            window = moving[steps - dy:steps - dy + cells, steps - dx:steps - dx + cells]
            windows[row, col] = (window, filled & np.isfinite(window))
    overlaps = np.zeros((len(offsets), len(offsets)), dtype=np.int64)
    for (row, col), (_, both) in windows.items():
        overlaps[row, col] = both.sum()
    # A shift that compares few cells fits by chance: count those within min_overlap of the largest overlap.
    enough = max(10, min_overlap * overlaps.max())
    costs = np.full(overlaps.shape, np.nan)
    for (row, col), (window, both) in windows.items():
        if overlaps[row, col] >= enough:
            difference = window[both] - fixed[both]
            costs[row, col] = np.sqrt(np.mean((difference - np.median(difference)) ** 2))
    if np.isnan(costs).all():
        raise ValueError(f"the clouds share fewer than 10 cells at every shift within {search:g} m")
    row, col = (int(i) for i in np.unravel_index(np.nanargmin(costs), costs.shape))
    shift = np.array([offsets[col] + cell * _vertex(costs[row, col - 1:col + 2]),
                      offsets[row] + cell * _vertex(costs[row - 1:row + 2, col])])
    gx, gy = np.meshgrid(offsets, offsets)
    far = (np.hypot(gx - offsets[col], gy - offsets[row]) > distinct) & np.isfinite(costs)
    runner_up = float(costs[far].min()) if far.any() else float("inf")
    difference = windows[row, col][0] - fixed
    vertical = float(np.median(difference[windows[row, col][1]]))
    return HeightMatch(shift, -vertical, float(costs[row, col]), runner_up, distinct, int(overlaps[row, col]),
                       offsets, costs)


def _vertex(three: np.ndarray) -> float:
    """Where a parabola through three equally spaced costs (the middle one lowest) has its minimum, in
    steps from the middle; 0 at the search's edge or where a neighbour is missing."""
    if len(three) != 3 or not np.isfinite(three).all():
        return 0.0
    curvature = three[0] - 2 * three[1] + three[2]
    return float(np.clip(0.5 * (three[0] - three[2]) / curvature, -0.5, 0.5)) if curvature > 0 else 0.0
