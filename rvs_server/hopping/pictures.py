"""Pictures of the hopping products: arrays in, RGB arrays out, each with its legend (the commands
write them). Grids are shown north up (toolbox/grid.py counts rows northwards).

    contact_sheet        a few frames of a hop with their times
    trajectory_picture   side view of a hop: centres of mass from SfM, the fitted parabola, the ground
    plan pictures        top-down map, height, obstacle mask, safe-landing mask, selection map
    global_maps          all hops' clouds: true colour and false colour by hop (the paper's Fig 18)
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from rvs_server.hopping.estimate import HopEstimate, flight_positions
from rvs_server.products.canvas import sheet
from toolbox.colour import NO_DATA_RGB, colourise, upscale, with_colour_bar, with_key, with_title
from toolbox.geometry import apply, invert
from toolbox.grid import GridSpec
from toolbox.hopping import LandingPlan, top_down_maps

HOP_COLOURS = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
               (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212)]
START_RGB, TARGET_RGB, PATH_RGB, ELLIPSE_RGB = (0, 255, 0), (255, 0, 255), (255, 255, 255), (0, 230, 255)
OBSTACLE_RGB, CLEAR_RGB, SAFE_RGB, UNSAFE_RGB = (220, 60, 50), (150, 150, 160), (70, 190, 70), (240, 160, 40)
TEXT_RGB = (235, 235, 235)
TILE_WIDTH = 320   # pixels of a contact-sheet frame


def hop_colour(number: int) -> tuple[int, int, int]:
    return HOP_COLOURS[(number - 1) % len(HOP_COLOURS)]


def _text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.4) -> None:
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, TEXT_RGB, 1, cv2.LINE_AA)


# ------------------------------------------------------------------------------------ frames
def contact_sheet(frames: np.ndarray, timestamps: np.ndarray, count: int, columns: int = 4) -> np.ndarray:
    """`count` frames spread evenly over the flight (first and last included), labelled with index and time."""
    chosen = np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))
    tiles = []
    for index in chosen:
        tile = cv2.cvtColor(frames[index], cv2.COLOR_GRAY2RGB) if frames[index].ndim == 2 else frames[index].copy()
        if tile.shape[1] > TILE_WIDTH:   # a sheet of full 640x480 frames would be megabytes
            tile = cv2.resize(tile, (TILE_WIDTH, round(tile.shape[0] * TILE_WIDTH / tile.shape[1])),
                              interpolation=cv2.INTER_AREA)
        tile = np.ascontiguousarray(upscale(tile, 240))
        cv2.rectangle(tile, (0, 0), (170, 20), (20, 20, 20), -1)
        _text(tile, f"#{index}  t = {timestamps[index]:.3f} s", (4, 14))
        tiles.append(tile)
    return sheet(tiles, columns)


# ------------------------------------------------------------------------------------ side view
class Plot:
    """An equal-aspect x-z canvas in metres, with a grid every `step` metres."""

    def __init__(self, x_range, z_range, width: int = 760, height: int = 380, margin: int = 44):
        self.image = np.full((height, width, 3), 25, np.uint8)
        self.margin = margin
        span_x, span_z = max(x_range[1] - x_range[0], 1e-3), max(z_range[1] - z_range[0], 1e-3)
        self.scale = min((width - 2 * margin) / span_x, (height - 2 * margin) / span_z)
        self.x0, self.z0, self.height = x_range[0], z_range[0], height
        self._grid(x_range, z_range)

    def pixel(self, x, z) -> np.ndarray:
        return np.column_stack([self.margin + (np.asarray(x) - self.x0) * self.scale,
                                self.height - self.margin - (np.asarray(z) - self.z0) * self.scale]).astype(np.int32)

    def _grid(self, x_range, z_range) -> None:
        step = _nice_step(max(x_range[1] - x_range[0], z_range[1] - z_range[0]) / 6)
        for x in np.arange(math.ceil(x_range[0] / step), math.floor(x_range[1] / step) + 1) * step:
            (u, v0), (_, v1) = self.pixel([x, x], [z_range[0], z_range[1]])
            cv2.line(self.image, (u, v0), (u, v1), (55, 55, 55), 1)
            _text(self.image, f"{x:g}", (u - 8, self.height - self.margin + 16))
        for z in np.arange(math.ceil(z_range[0] / step), math.floor(z_range[1] / step) + 1) * step:
            (u0, v), (u1, _) = self.pixel([x_range[0], x_range[1]], [z, z])
            cv2.line(self.image, (u0, v), (u1, v), (55, 55, 55), 1)
            _text(self.image, f"{z:g}", (4, v + 4))

    def dots(self, x, z, colour, radius: int = 1) -> None:
        """A filled disk of `radius` pixels at each point, all points at once: a cv2.circle per point
        was 40 % of the time hop-plan held the interpreter in the server (py-spy, profile_job_gil.py),
        time a status reply waited for."""
        pixels = self.pixel(x, z)
        rows, cols = self.image.shape[:2]
        for du in range(-radius, radius + 1):
            for dv in range(-radius, radius + 1):
                if du * du + dv * dv > radius * radius:
                    continue
                u, v = pixels[:, 0] + du, pixels[:, 1] + dv
                inside = (u >= 0) & (u < cols) & (v >= 0) & (v < rows)
                self.image[v[inside], u[inside]] = colour

    def line(self, x, z, colour, thickness: int = 1) -> None:
        cv2.polylines(self.image, [self.pixel(x, z)], False, colour, thickness, cv2.LINE_AA)


def _nice_step(raw: float) -> float:
    power = 10 ** math.floor(math.log10(max(raw, 1e-6)))
    return next(m * power for m in (1, 2, 5, 10) if m * power >= raw)


def trajectory_picture(estimate: HopEstimate, title: str) -> np.ndarray:
    """Side view in the hop frame (x along the flight, z up, metres): SfM centres of mass (inliers white,
    outliers red), the fitted parabola to the touchdown, and the cloud within 10 cm of the flight plane."""
    flight = estimate.result.flight
    taus = np.linspace(0.0, estimate.touchdown_tau, 200)
    curve = flight_positions(flight.launch_velocity, taus, estimate.gravity)
    ground = apply(invert(estimate.to_world), estimate.result.cloud)
    ground = ground[np.abs(ground[:, 1]) < 0.1]
    points = np.vstack([estimate.com_hop, curve])
    x_range = (min(points[:, 0].min(), 0.0) - 0.2, points[:, 0].max() + 0.4)
    z_low = float(np.percentile(ground[:, 2], 1)) if len(ground) else points[:, 2].min()
    z_range = (min(z_low, points[:, 2].min()) - 0.1, points[:, 2].max() + 0.15)
    plot = Plot(x_range, z_range)
    inside = (ground[:, 0] > x_range[0]) & (ground[:, 0] < x_range[1])
    plot.dots(ground[inside, 0], ground[inside, 2], (110, 110, 110))
    plot.line(curve[:, 0], curve[:, 2], (255, 210, 0), 2)
    inlier = flight.inliers
    plot.dots(estimate.com_hop[inlier, 0], estimate.com_hop[inlier, 2], (255, 255, 255), 2)
    plot.dots(estimate.com_hop[~inlier, 0], estimate.com_hop[~inlier, 2], OBSTACLE_RGB, 3)
    end = curve[-1]
    plot.dots([end[0]], [end[2]], TARGET_RGB, 5)
    keyed = with_key(plot.image, [("centre of mass (SfM)", (255, 255, 255)), ("outlier", OBSTACLE_RGB),
                                  ("fitted parabola", (255, 210, 0)), ("touchdown", TARGET_RGB),
                                  ("cloud near the flight plane", (110, 110, 110))],
                     f"hop frame: x along the flight, z up, metres; scale {flight.scale:.4g} m/unit, "
                     f"v {flight.launch_speed:.3f} m/s at {math.degrees(flight.launch_elevation):.1f} deg")
    return with_title(keyed, title)


# ------------------------------------------------------------------------------------ grid pictures
class GridCanvas:
    """A grid picture north up, enlarged to a readable size, with world-to-pixel for drawing on it."""

    def __init__(self, grid_rgb: np.ndarray, spec: GridSpec, min_size: int = 480):
        self.spec = spec
        self.factor = max(1, int(math.ceil(min_size / max(grid_rgb.shape[:2]))))
        self.image = np.ascontiguousarray(upscale(np.flipud(grid_rgb), min_size))

    def pixel(self, xy) -> tuple[int, int]:
        spec = self.spec
        col = (xy[0] - spec.origin_x) / spec.cell * self.factor
        row = (spec.rows - (xy[1] - spec.origin_y) / spec.cell) * self.factor
        return int(round(col)), int(round(row))

    def metres(self, length: float) -> int:
        return max(1, int(round(length / self.spec.cell * self.factor)))

    def marker(self, xy, colour, kind: str = "circle", size: int = 6) -> None:
        if kind == "circle":
            cv2.circle(self.image, self.pixel(xy), size, colour, 2, cv2.LINE_AA)
        else:
            cv2.drawMarker(self.image, self.pixel(xy), colour, cv2.MARKER_CROSS if kind == "cross" else
                           cv2.MARKER_TILTED_CROSS, 2 * size, 2)

    def polyline(self, xy: np.ndarray, colour, thickness: int = 1) -> None:
        if len(xy) > 1:
            cv2.polylines(self.image, [np.array([self.pixel(p) for p in xy], np.int32)], False, colour, thickness,
                          cv2.LINE_AA)

    def ellipse(self, centre, axes: tuple[float, float], heading: float, colour) -> None:
        """Semi-axes (along, across) in metres, the major one along `heading` (rad, CCW from east)."""
        cv2.ellipse(self.image, self.pixel(centre), (self.metres(axes[0]), self.metres(axes[1])),
                    -math.degrees(heading), 0, 360, colour, 2, cv2.LINE_AA)


def _grid_title(spec: GridSpec) -> str:
    return (f"{spec.cols * spec.cell:.1f} x {spec.rows * spec.cell:.1f} m, cell {spec.cell * 100:.1f} cm, "
            f"origin ({spec.origin_x:.2f}, {spec.origin_y:.2f}), north up")


def colour_grid(colour: np.ndarray | None, count: np.ndarray) -> np.ndarray:
    """Mean colour per cell as uint8 RGB, no-data grey where nothing fell."""
    if colour is None:
        rgb = np.zeros(count.shape + (3,), np.uint8)
    else:
        rgb = np.clip(np.nan_to_num(colour[..., :3] if colour.shape[-1] >= 3 else np.repeat(colour, 3, axis=2)),
                      0, 255).astype(np.uint8)
    rgb[count == 0] = NO_DATA_RGB
    return rgb


def plan_pictures(plan: LandingPlan, start: np.ndarray, title: str) -> dict[str, np.ndarray]:
    """The plan's maps: top-down colour, height, obstacle mask, safe-landing mask, selection map."""
    spec = plan.spec
    top = plan.top_down
    height = top.height
    finite = height[np.isfinite(height)]
    low, high = (float(np.percentile(finite, 1)), float(np.percentile(finite, 99))) if finite.size else (0.0, 1.0)
    hazard = plan.obstacle | ~plan.known
    obstacle_rgb = np.where(plan.obstacle[..., None], OBSTACLE_RGB, CLEAR_RGB).astype(np.uint8)
    obstacle_rgb[~plan.known & ~plan.obstacle] = NO_DATA_RGB
    safe_rgb = obstacle_rgb.copy()
    reachable = plan.goal > 0
    safe_rgb[reachable & ~plan.safe & ~hazard] = UNSAFE_RGB
    safe_rgb[plan.safe] = SAFE_RGB
    grid = _grid_title(spec)
    pictures = {
        "topdown.png": with_key(_marked(colour_grid(top.colour, top.count), plan, start, False),
                                [("start", START_RGB), ("no data", NO_DATA_RGB)], "top-down map: mean grey level"),
        "height.png": with_colour_bar(_marked(colourise(height, low, high), plan, start, False), low, high,
                                      "highest point per cell, m (heights relative to the start's ground)"),
        "obstacles.png": with_key(_marked(obstacle_rgb, plan, start, False),
                                  [("obstacle", OBSTACLE_RGB), ("clear", CLEAR_RGB), ("unseen", NO_DATA_RGB),
                                   ("start", START_RGB)],
                                  "obstacles: protrusion over the ground plane, median filter and closing"),
        "safe.png": with_key(_marked(safe_rgb, plan, start, True),
                             [("safe: whole ellipse clear", SAFE_RGB), ("reachable, ellipse not clear", UNSAFE_RGB),
                              ("obstacle", OBSTACLE_RGB), ("clear, out of reach", CLEAR_RGB), ("unseen", NO_DATA_RGB),
                              ("target + ellipse", ELLIPSE_RGB)], "safe-landing mask"),
        "selection.png": with_key(with_colour_bar(_marked(_selection_rgb(plan, hazard), plan, start, True), 0.0, 1.0,
                                                  "selection score (clearance and goal blended)", cmap="viridis"),
                                  [("start", START_RGB), ("target", TARGET_RGB), ("error ellipse", ELLIPSE_RGB),
                                   ("planned flight", PATH_RGB), ("rejected candidate", UNSAFE_RGB),
                                   ("hazard", OBSTACLE_RGB)], "selection map"),
    }
    return {name: with_title(picture, f"{title}: {grid}") for name, picture in pictures.items()}


def _selection_rgb(plan: LandingPlan, hazard: np.ndarray) -> np.ndarray:
    score = plan.score
    finite = score[np.isfinite(score)]
    rgb = colourise(score, 0.0, float(finite.max()) if finite.size else 1.0, "viridis")
    rgb[~np.isfinite(score)] = (45, 45, 55)
    rgb[hazard] = (120, 35, 30)
    return rgb


def _marked(grid_rgb: np.ndarray, plan: LandingPlan, start: np.ndarray, with_target: bool) -> np.ndarray:
    canvas = GridCanvas(grid_rgb, plan.spec)
    canvas.marker(start, START_RGB)
    if with_target and plan.found:
        canvas.polyline(plan.trajectory[:, :2], PATH_RGB, 1)
        heading = math.atan2(plan.target[1] - start[1], plan.target[0] - start[0])
        canvas.ellipse(plan.target, plan.ellipse_axes, heading, ELLIPSE_RGB)
        canvas.marker(plan.target, TARGET_RGB, "cross", 8)
    if with_target:
        for x, y, _ in plan.rejected:
            canvas.marker((x, y), UNSAFE_RGB, "tilted", 4)
    return canvas.image


def truth_target_picture(obstacles: np.ndarray, plan: LandingPlan, start: np.ndarray, title: str) -> np.ndarray:
    """The simulator's obstacles on the plan's grid with the estimated start, target and ellipse."""
    rgb = np.where(obstacles[..., None], OBSTACLE_RGB, CLEAR_RGB).astype(np.uint8)
    return with_title(with_key(_marked(rgb, plan, start, True),
                               [("true obstacle", OBSTACLE_RGB), ("clear", CLEAR_RGB), ("target", TARGET_RGB),
                                ("error ellipse", ELLIPSE_RGB), ("estimated start", START_RGB)],
                               "truth: obstacles (world obstacle_mask)"), f"{title}: {_grid_title(plan.spec)}")


# ------------------------------------------------------------------------------------ global map
def global_maps(clouds: list[tuple[int, np.ndarray, np.ndarray | None]], tracks: list[tuple[int, np.ndarray]],
                cell: float, title: str) -> tuple[np.ndarray, np.ndarray, GridSpec, np.ndarray]:
    """All hops' clouds on one top-down grid (paper Fig 18): (true colour picture, false colour picture
    by hop, grid, (rows, cols) hops-per-cell count). clouds: (hop number, points, colours); tracks:
    (hop number, (K, 3) estimated flight) drawn on both. A cell seen by several hops mixes their colours."""
    points = np.vstack([p for _, p, _ in clouds])
    extent = np.vstack([points[:, :2], *(track[:, :2] for _, track in tracks if len(track))])
    low, high = extent.min(axis=0) - 0.25, extent.max(axis=0) + 0.25
    cell = max(cell, float((high - low).max()) / 2000)   # a stray point must not make the grid huge
    spec = GridSpec.covering((low[0], high[0]), (low[1], high[1]), cell)
    colours = np.vstack([c if c is not None else np.full((len(p), 3), 128, np.uint8) for _, p, c in clouds])
    true = top_down_maps(points, spec, colours)
    seen = np.zeros(spec.shape, int)
    false_sum = np.zeros(spec.shape + (3,))
    for number, cloud, _ in clouds:
        mask = top_down_maps(cloud, spec).count > 0
        seen += mask
        false_sum[mask] += hop_colour(number)
    false_rgb = (false_sum / np.maximum(seen, 1)[..., None]).astype(np.uint8)
    false_rgb[seen == 0] = NO_DATA_RGB
    pictures = []
    # Flights in their hop's colour on the grey map; white on the false-colour one, where hop colours are the ground.
    for rgb, flight_colour in ((colour_grid(true.colour, true.count), hop_colour), (false_rgb, lambda _: PATH_RGB)):
        canvas = GridCanvas(rgb, spec, 640)
        for number, track in tracks:
            canvas.polyline(track[:, :2], flight_colour(number), 2)
            canvas.marker(track[-1], TARGET_RGB, "cross", 5)
        pictures.append(canvas.image)
    key = [(f"hop {number}", hop_colour(number)) for number, _, _ in clouds]
    grid = _grid_title(spec)
    true_picture = with_title(with_key(pictures[0], key + [("landing (estimated)", TARGET_RGB)],
                                       "true colour (the camera's grey levels); flights in their hop's colour"),
                              f"{title}: {grid}")
    false_picture = with_title(with_key(pictures[1], key + [("flight", PATH_RGB), ("no data", NO_DATA_RGB)],
                                        "false colour: which hop saw each cell (mixed colours: several)"),
                               f"{title}: {grid}")
    return true_picture, false_picture, spec, seen
