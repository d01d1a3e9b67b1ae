"""The record of a traverse: traverse.json, the simulator's truth, and the overview picture.

The overview shows the fused map of every cycle (cost, grown hazards, unknown) with the path as the
rover believed it (white, map-corrected), as dead reckoning alone would have had it (yellow) and,
simulated, as it really went (magenta), each cycle's mapping position numbered, start and goal. A
second panel shows the simulator's true obstacles with the true path, and the rover's footprint
wherever it touched one.
"""
from __future__ import annotations

import math
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from rvs_server.products.canvas import Canvas as GridCanvas
from rvs_server.products.canvas import side_by_side
from rvs_server.products.rasters import write_png
from toolbox.colour import categorical, colourise, with_key, with_title
from toolbox.grid import GridSpec
from toolbox.planning import MapLayers

if TYPE_CHECKING:
    from rvs_server.jobs import JobContext

PICTURE_SIZE = 720
WHITE, YELLOW, MAGENTA, GREEN, CYAN = (255, 255, 255), (250, 210, 40), (255, 60, 255), (60, 230, 60), (0, 230, 255)


def write_traverse(ctx: JobContext, product: Any, state: Any, goal: tuple[float, float], outcome: str, message: str,
                   fused: MapLayers | None, truth: dict | None) -> None:
    record = asdict(state)
    record.pop("true_path", None)
    record.pop("contacts", None)
    product.write_json("traverse.json", {"outcome": outcome, "message": message, "goal": list(goal),
                                         "frame": "world: x east, y north, metres; headings radians CCW from east",
                                         **record},
                       "the traverse: outcome, every cycle's localisation and plan, estimated and dead-reckoning paths")
    if truth is not None:
        product.write_json("truth/traverse.json", truth, "simulator truth: the rover's true path (x, y, heading) "
                           "and how many path samples had its footprint over a true obstacle")
    if fused is None:
        return
    panels = [map_panel(fused, state, goal, truth)]
    if truth is not None:
        obstacles = truth_panel(ctx, fused.spec, truth, goal, state)
        if obstacles is not None:
            panels.append(obstacles)
    picture = side_by_side(panels)
    title = f"{product.name}: {outcome}" + (f" ({message})" if message else "")
    write_png(product.add("overview.png", "the whole traverse: fused map with the estimated, dead-reckoning "
                          "and (simulated) true paths; true obstacles beside it"), with_title(picture, title[:160]))


class Canvas(GridCanvas):
    """The traverse pictures' canvas: start and goal marked alike on both panels."""

    def __init__(self, rgb: np.ndarray, spec: GridSpec):
        super().__init__(rgb, spec, PICTURE_SIZE)

    def ends(self, start, goal) -> None:
        cv2.circle(self.image, self.pixel(start), 7, GREEN, 2)
        cv2.drawMarker(self.image, self.pixel(goal), MAGENTA, cv2.MARKER_CROSS, 16, 2)


def map_panel(fused: MapLayers, state: Any, goal, truth: dict | None) -> np.ndarray:
    cost = np.where(fused.hazard, np.nan, fused.cost)
    finite = cost[np.isfinite(cost)]
    rgb = colourise(cost, 0.0, float(np.percentile(finite, 99)) if finite.size else 1.0, "viridis")
    rgb[fused.unknown] = (95, 95, 95)
    rgb[fused.hazard] = (200, 50, 40)
    canvas = Canvas(rgb, fused.spec)
    canvas.line([p[:2] for p in state.odometry_path], YELLOW, 1)
    if truth is not None:
        canvas.line([p[:2] for p in truth["path"]], MAGENTA, 2)
    canvas.line([p[:2] for p in state.estimated_path], WHITE, 2)
    for record in state.cycles:
        x, y = record["pose_corrected"][:2]
        cv2.circle(canvas.image, canvas.pixel((x, y)), 4, CYAN, -1)
        cv2.putText(canvas.image, str(record["cycle"]), canvas.pixel((x + 0.15, y + 0.15)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, CYAN, 1, cv2.LINE_AA)
    canvas.ends(state.start, goal)
    key = [("estimated path", WHITE), ("dead reckoning", YELLOW), ("cycle: map here", CYAN),
           ("hazard", (200, 50, 40)), ("unknown", (95, 95, 95)), ("start / goal", GREEN)]
    if truth is not None:
        key.insert(1, ("true path", MAGENTA))
    return with_key(canvas.image, key, "fused map of every cycle (cost: dark low, yellow high)")


def truth_panel(ctx: JobContext, spec: GridSpec, truth: dict, goal, state: Any) -> np.ndarray | None:
    world = ctx.devices.truth
    if world is None or spec.cell < world.cell:
        return None
    obstacles = world.obstacle_mask(truth["step_height_m"], spec.cell, spec.x_range, spec.y_range)
    rgb = categorical(obstacles[:spec.rows, :spec.cols].astype(np.uint8), {0: (70, 160, 70), 1: (220, 60, 50)})
    canvas = Canvas(rgb, spec)
    canvas.line([p[:2] for p in truth["path"]], MAGENTA, 2)
    rover = ctx.devices.rover
    length, width = rover.true_body_m()
    for x, y, heading in truth["path"][::4]:
        if rover.truly_touches(x, y, heading, truth["step_height_m"]):
            corners = _corners(x, y, heading, length, width)
            cv2.polylines(canvas.image, [canvas.pixels(corners)], True, WHITE, 1)
    canvas.ends(state.start, goal)
    return with_key(canvas.image, [("clear", (70, 160, 70)), (f"rock > {truth['step_height_m']} m", (220, 60, 50)),
                                   ("true path", MAGENTA), ("footprint on a rock", WHITE)],
                    f"truth: obstacles; {truth['contacts']} path samples touched one")


def _corners(x: float, y: float, heading: float, length: float, width: float) -> np.ndarray:
    local = np.array([[length / 2, width / 2], [-length / 2, width / 2], [-length / 2, -width / 2],
                      [length / 2, -width / 2]])
    c, s = math.cos(heading), math.sin(heading)
    return np.array([x, y]) + local @ np.array([[c, -s], [s, c]]).T

