"""Cost grids for the planner: terrain cost from slope and roughness, hazards grown by the rover's size,
a soft cost near hazards, and the policy for cells nobody has seen.

Costs follow the metric of planning_search: >= 0 per cell, 0 for flat easy ground, 1 at the rover's
slope or roughness limit, +inf where the rover must not go. Distances are in metres, measured
between cell centres.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.ndimage import distance_transform_edt

UnknownPolicy = Literal["forbid", "allow", "penalize"]
UNKNOWN_POLICIES: tuple[str, ...] = ("forbid", "allow", "penalize")


def terrain_cost(slope: np.ndarray, slope_limit: float, roughness: np.ndarray | None = None,
                 roughness_limit: float | None = None) -> np.ndarray:
    """Cost in [0, 1] per cell: the larger of slope / slope_limit and roughness / roughness_limit.

    The worse of the two decides, as either one alone can stop the rover. Cells at or over a limit
    cost 1; whether they are hazards is the hazard map's call, not this function's. NaN in an input
    (no data) stays NaN, for the unknown policy to resolve."""
    if not slope_limit > 0:
        raise ValueError(f"slope limit must be > 0, got {slope_limit!r}")
    cost = np.abs(np.asarray(slope, dtype=np.float64)) / slope_limit
    if roughness is not None:
        if roughness_limit is None or not roughness_limit > 0:
            raise ValueError(f"roughness limit must be > 0, got {roughness_limit!r}")
        roughness = np.asarray(roughness, dtype=np.float64)
        if roughness.shape != cost.shape:
            raise ValueError(f"slope {cost.shape} and roughness {roughness.shape} grids differ in shape")
        # np.maximum propagates NaN: a cell is known only if both its slope and its roughness are.
        cost = np.maximum(cost, roughness / roughness_limit)
    return np.clip(cost, 0.0, 1.0)


@dataclass(frozen=True)
class InflatedHazards:
    mask: np.ndarray        # bool: hazard cells and every cell within the clearance of one
    distance_m: np.ndarray  # metres from each cell centre to the nearest hazard cell centre; inf if none
    clearance_m: float      # the radius the hazards were grown by


def inflate_hazards(hazard: np.ndarray, cell: float, clearance_m: float) -> InflatedHazards:
    """Grow hazards by `clearance_m` (the rover's radius plus a margin) with a Euclidean distance transform.

    The path is planned for the rover's centre, so a cell is blocked when its centre lies within the
    clearance of a hazard cell's centre. The distance map is returned too, for a soft cost near hazards."""
    hazard = np.asarray(hazard, dtype=bool)
    if not cell > 0:
        raise ValueError(f"cell size must be > 0, got {cell!r}")
    if not clearance_m >= 0:
        raise ValueError(f"clearance must be >= 0 m, got {clearance_m!r}")
    if hazard.any():
        distance_cells = distance_transform_edt(~hazard)
    else:
        distance_cells = np.full(hazard.shape, np.inf)
    # Compare in cells so 3 * 0.1 m is within 0.3 m despite rounding.
    mask = distance_cells <= clearance_m / cell + 1e-9
    return InflatedHazards(mask, distance_cells * cell, float(clearance_m))


def proximity_cost(distance_m: np.ndarray, clearance_m: float, falloff_m: float) -> np.ndarray:
    """Soft cost near hazards, in [0, 1]: 1 at the clearance, falling linearly to 0 `falloff_m` beyond.

    It steers paths away from hazards where room allows, rather than grazing the inflated edge.
    A falloff of 0 switches it off."""
    if not falloff_m >= 0:
        raise ValueError(f"falloff must be >= 0 m, got {falloff_m!r}")
    distance_m = np.asarray(distance_m, dtype=np.float64)
    if falloff_m == 0:
        return np.zeros(distance_m.shape)
    return np.clip(1.0 - (distance_m - clearance_m) / falloff_m, 0.0, 1.0)


def apply_unknown_policy(cost: np.ndarray, unknown: np.ndarray, policy: UnknownPolicy,
                         unknown_cost: float = 0.0) -> np.ndarray:
    """Give unknown cells a cost: "forbid" +inf, "allow" 0 (as flat ground), "penalize" `unknown_cost`.

    An unknown cell has no terrain to cost, so it starts as flat ground and "penalize" adds the
    configured extra. Like all terrain cost it weighs (1 - w): at w = 1 only "forbid" changes a path."""
    cost = np.asarray(cost, dtype=np.float64)
    unknown = np.asarray(unknown, dtype=bool)
    if cost.shape != unknown.shape:
        raise ValueError(f"cost {cost.shape} and unknown {unknown.shape} grids differ in shape")
    if np.isnan(cost[~unknown]).any():
        raise ValueError("known cells hold NaN cost; mark them unknown")
    values = {"forbid": np.inf, "allow": 0.0, "penalize": float(unknown_cost)}
    if policy not in values:
        raise ValueError(f"unknown-cell policy must be one of {', '.join(UNKNOWN_POLICIES)}, got {policy!r}")
    if not values[policy] >= 0:
        raise ValueError(f"unknown-cell cost must be >= 0, got {unknown_cost!r}")
    return np.where(unknown, values[policy], cost)
