"""Path planning on the maps: plan-path, and pose (the GNC telling the server where the rover is).

plan-path fuses a global map (a blank one spanning start and goal; unknown until seen) with the
latest local hazard map at their own cell sizes, plans the exact least-cost path with A*, simplifies
it into straight segments that stay clear of the grown hazards, and hands out only the part inside
the local map and at least a margin from its border. The product holds the cost map with the path
and waypoints drawn on it, the same on the ortho-image, and the waypoints as JSON and CSV.
"""
from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, PositiveFloat, ValidationError, model_validator
from scipy.ndimage import binary_fill_holes

from rvs_server.config import CommandConfig, PerSensor, Point, Range, SafeName, Settings, TypeLabel
from rvs_server.devices import DriveError
from rvs_server.dispatch import Call, Module
from rvs_server.files import atomic_file
from rvs_server.jobs import JobContext
from rvs_server.products.canvas import Canvas
from rvs_server.products.rasters import read_geotiff, write_geotiff, write_png
from rvs_server.protocol import BadRequest, WrongMode
from toolbox.colour import colourise, with_colour_bar, with_title
from toolbox.geometry import RoverPose
from toolbox.grid import GridSpec
from toolbox.mapping.hazard import HAZARD, UNKNOWN
from toolbox.planning import (
    MapLayers,
    PlanningParams,
    blank_map_spanning,
    cells_to_world,
    distance_to_border,
    drivable_prefix,
    enclosed_unknown,
    fuse_maps,
    inside_box,
    outside_box,
    plan_path,
    terrain_cost,
    with_hazards,
)

if TYPE_CHECKING:
    from rvs_server.host import Host

Metres = Annotated[float, Field(ge=0)]
Length = Annotated[float, Field(gt=0)]
FarHazardPolicy = Literal["hazard", "unconfirmed"]
HolePolicy = Literal["hazard", "unknown"]


class OperatingArea(BaseModel):
    """A box in the world frame, metres, that the rover keeps inside."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    x: Range
    y: Range

    @property
    def box(self) -> tuple[float, float, float, float]:
        return (*self.x, *self.y)


AREA_NAMES = ("world", "none")


def _area(value: Any) -> OperatingArea | str:
    """navigation.toml operating_area: "world", "none" or a table {x = [A, B], y = [C, D]}; one
    message for what is wrong, not one per reading of it."""
    if isinstance(value, OperatingArea) or value in AREA_NAMES:
        return value
    if not isinstance(value, dict):
        raise ValueError("neither a name nor a table")
    try:
        return OperatingArea.model_validate(value)
    except ValidationError as exc:
        raise ValueError("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg'].removeprefix('Value error, ')}"
                                   for e in exc.errors(include_url=False))) from None


AreaSetting = Annotated[Any, PlainValidator(_area), TypeLabel("world|none|{x = [A, B], y = [C, D]}")]


class NavigationSettings(Settings):
    weight: float = Field(0.5, ge=0, le=1, description="1: shortest path; 0: easiest ground")
    rover_radius_m: float = Field(0.3, gt=0, description="hazards grow by this plus the margin")
    hazard_margin_m: PerSensor[Metres] = Field(
        PerSensor[Metres](tof=0.05, stereo=0.05), description="per sensor (or one for both), the map's error at a "
        "rock's edge; the drive error has its own cut (drive_error_sigmas)")
    proximity_falloff_m: float = Field(0.4, ge=0, description="paths keep this much farther from hazards where "
                                       "room allows (a soft cost); 0: off")
    proximity_cost: float = Field(1.0, ge=0, description="the soft cost at the grown hazards' edge")
    unknown_policy: Literal["forbid", "allow", "penalize"] = "penalize"
    unknown_cost: float = Field(0.5, ge=0)
    max_deviation_m: float = Field(0.1, gt=0, description="straight segments stay this close to the A* path")
    border_margin_m: float = Field(0.5, ge=0, description="waypoints handed out keep this far from the "
                                   "local map's border")
    global_cell_m: float = Field(0.05, gt=0, description="cell of the blank global map")
    global_margin_m: float = Field(3.0, ge=0, description="the global map spans start and goal plus this")
    max_reach_m: float = Field(100.0, gt=0, le=1000, description="goals farther from the start are refused")
    operating_area: AreaSetting = Field(
        "world", description="where the rover may go, {x = [A, B], y = [C, D]} in world metres: ground outside is "
        "a hazard, and goals outside are refused; world: the simulated world's extent (no bound with real devices); "
        "none: no bound")
    slope_limit_deg: float = Field(20.0, gt=0, lt=90, description="terrain cost 1 at this slope")
    roughness_limit: float = Field(0.04, gt=0, description="terrain cost 1 at this roughness")
    # navigate
    drive: Literal["auto", "simulated", "gnc"] = Field(
        "auto", description="who drives navigate's waypoints: the simulated rover, or the GNC (waypoints as a "
        "navigate event, then wait for pose); auto: simulated when the devices are")
    first_pan: Range = Field((-180.0, 180.0), description="pan range of the first cycle's map (and after a stall)")
    cycle_pan: Range = Field((-180.0, 180.0), description="pan range of later cycles' maps, relative to the rover")
    max_drive_m: PerSensor[Length] = Field(PerSensor[Length](tof=3.0, stereo=3.0), description="per sensor (or "
                                           "one for both), drive at most this far before mapping again")
    drive_error: DriveError = Field(DriveError(), description="standard deviations of the rover's open-loop "
                                    "motion errors between two maps, as its GNC states them")
    drive_error_sigmas: float = Field(3.0, ge=0, description="a drive ends where this many standard deviations of "
                                      "its error exceed the room between the footprint and the hazards; 0: off")
    footprint_m: tuple[PositiveFloat, PositiveFloat] = Field((0.55, 0.50), description="the rover's footprint, "
                                                             "length x width, metres, for the drive-error cut")
    orient: PerSensor[bool] = Field(
        PerSensor[bool](tof=False, stereo=True), description="per sensor (or one for both), each cycle begins "
        "with an orient look along the heading (visual odometry since the last cycle's, the sun's heading; "
        "orient.toml): the map alignment starts from it instead of dead reckoning; and the drives look every "
        "orient_step_m")
    orient_step_m: float = Field(1.0, gt=0.1, le=10, description="with orient, a drive's legs are cut into parts "
                                 "of at most this length with an orient look after each: the rover re-aims at the "
                                 "next waypoint from where it is, not from where dead reckoning says")
    orient_turn_deg: float = Field(20.0, gt=1, le=180, description="with orient, a larger turn is made in parts "
                                   "of at most this, a look after each: the views either side must overlap")
    route_hysteresis: float = Field(0.25, ge=0, description="navigate keeps its last route while it is clear and "
                                    "costs at most this fraction more than a new plan; 0: replan from scratch")
    min_progress_m: float = Field(0.15, gt=0, description="a safe part shorter than this is a stall")
    step_limit_m: float = Field(0.09, gt=0, description="navigate's maps call a step hazardous from this "
                                "height: below the rover's limit by the sensors' height error")
    tilt: PerSensor[Range] = Field(
        PerSensor[Range](tof=(-62.0, -28.0), stereo=(-62.0, -20.0)), description="per sensor, the elevations "
        "navigate's panoramas cover, degrees: down to the ground beside the rover, which it drives over next")
    blind_radius_m: PerSensor[Metres] = Field(
        PerSensor[Metres](tof=0.9, stereo=1.0), description="per sensor, the ring round the mast it cannot see: "
        "counts as seen when the part of the path to hand out is cut, and is no hole where the rover started")
    holes: PerSensor[HolePolicy] = Field(
        PerSensor[HolePolicy](tof="unknown", stereo="hazard"), description="per sensor, unknown cells walled in "
        "by known ground (nothing came back from a place the sensor looked at): hazard, or unknown like the "
        "unexplored outside")
    look_first: PerSensor[bool] = Field(
        PerSensor[bool](tof=True, stereo=False), description="per sensor, navigate stops a drive blind_radius_m + "
        "border_margin_m short of the first unknown ground its path crosses that no cycle has looked at from "
        "within close_look_m: once the rover stands beside it, in the sensor's blind ring, no look can see it")
    close_look_m: float = Field(2.0, gt=0, description="look_first: unknown ground a cycle has looked at from this "
                                "close (beyond the sensor's blind ring) is a shadow, needing no other look")
    min_hole_m2: float = Field(0.01, ge=0, description="smaller holes stay unknown")
    far_hazards: PerSensor[FarHazardPolicy] = Field(
        PerSensor[FarHazardPolicy](tof="hazard", stereo="unconfirmed"), description="per sensor, hazards seen only "
        "from beyond confirm_range_m: hazard like any other, or unconfirmed (see look_again_detour)")
    sticky_range_m: float = Field(2.5, ge=0, description="a hazard any cycle saw from this close stays, "
                                  "whatever a nearer look says")
    confirm_range_m: float = Field(3.0, gt=0, description="a hazard seen only from farther than this is "
                                   "unconfirmed (see look_again_detour), and a goal seen blocked from farther is "
                                   "approached and looked at again before navigate refuses it")
    look_again_detour: float = Field(0.25, ge=0, description="when the way round unconfirmed ground (holes, "
                                     "hazards seen only from afar) is this much longer than the way through it, "
                                     "or there is no way round, the rover drives towards it and looks again")
    pose_timeout_s: float = Field(900.0, gt=0, description="how long navigate waits for the GNC's pose")

    @model_validator(mode="after")
    def _close_look_reaches_past_the_stop(self) -> NavigationSettings:
        for sensor in ("tof", "stereo"):
            stop = look_distance(self, sensor)
            if self.look_first.of(sensor) and self.close_look_m <= stop:
                raise ValueError(f"close_look_m = {self.close_look_m:g} must exceed the {stop:g} m from which the "
                                 f"rover looks first ({sensor}: blind_radius_m + border_margin_m): else no look "
                                 "ever settles the ground it stops for")
        return self


module = Module("navigation", settings=NavigationSettings, summary="path planning and the rover's pose")


class PlanPathConfig(CommandConfig):
    from_: Point | None = Field(None, description="start X,Y in the world frame, metres; default the rover")
    to: Point = Field(..., description="goal X,Y in the world frame, metres")
    weight: float | None = Field(None, ge=0, le=1, description="distance weight w; default navigation.toml")
    sensor: Literal["tof", "stereo", "fused"] = Field("tof", description="whose latest map to plan on")
    output: SafeName | None = None


class PoseConfig(CommandConfig):
    pose: str = Field(..., description="X,Y,HEADING: metres, metres, degrees counter-clockwise from east")


LAST_MAP = {"tof": "dem-(full|update)-tof", "stereo": "dem-(full|update)", "fused": "dem-full-fused"}
FIRST_MAP = {"tof": "dem-full-tof", "stereo": "dem-full", "fused": "dem-full-fused"}


def local_map(server: Host, sensor: str) -> tuple[MapLayers, str, Path, dict[str, np.ndarray]]:
    """The latest hazard map of the sensor as planning layers, its name and folder, and its ortho-image."""
    name, folder = latest_map_folder(server, sensor)
    settings: NavigationSettings = server.settings_of("navigation")
    layers = planning_layers(folder, settings, server.devices.rover.pose_estimate)
    ortho = folder / "ortho.tif"
    extra = {"ortho": read_geotiff(ortho)[0] if ortho.exists() else np.full(layers.spec.shape, np.nan)}
    return layers, name, folder, extra


def latest_map_folder(server: Host, sensor: str) -> tuple[str, Path]:
    """The newer of the sensor's last dem-full/dem-update map and the last cycle's map of its last navigate
    run (a user who has just navigated expects plan-path to see what navigate saw), refused runs included:
    their maps are whole, only the traverse stopped."""
    candidates = []
    mapped = server.products.latest(LAST_MAP[sensor])
    if mapped is not None:
        candidates.append((mapped.path / "product.json", mapped.name, mapped.path))
    def same_sensor(data: dict) -> bool:
        return data.get("arguments", {}).get("sensor") == sensor

    navigated = server.products.latest("navigate", where=same_sensor, statuses=("complete", "failed"))
    cycles = sorted(navigated.path.glob("cycle-*/hazard.tif")) if navigated is not None else []
    if cycles:
        candidates.append((navigated.path / "product.json", f"{navigated.name}/{cycles[-1].parent.name}",
                           cycles[-1].parent))
    if not candidates:
        raise WrongMode(f"no {sensor} map yet: run {FIRST_MAP[sensor]} or navigate --sensor {sensor} first")
    _, name, folder = max(candidates, key=lambda c: c[0].stat().st_mtime)
    return name, folder


def planning_layers(folder: Path, settings: NavigationSettings, pose: RoverPose) -> MapLayers:
    """A map folder's hazard, slope and roughness GeoTIFFs as planning layers. The rover stands
    on its own footprint, which no sensor sees: that ground is known and safe."""
    code, spec = read_geotiff(folder / "hazard.tif")
    slope = read_geotiff(folder / "slope.tif")[0]
    roughness = read_geotiff(folder / "roughness.tif")[0]
    unknown = code == UNKNOWN
    hazard = ~unknown & ((code.astype(np.int64) & HAZARD) != 0)
    cost = terrain_cost(slope, settings.slope_limit_deg, roughness, settings.roughness_limit)
    cost = np.where(unknown | hazard, np.nan, np.nan_to_num(cost, nan=0.0))
    under = under_rover(spec, pose, settings.rover_radius_m)
    unknown &= ~under
    cost = np.where(under & np.isnan(cost) & ~hazard, 0.0, cost)
    return MapLayers(spec, np.where(unknown, np.nan, cost), hazard, unknown)


def under_rover(spec: GridSpec, pose: RoverPose, radius: float) -> np.ndarray:
    xs, ys = spec.centres()
    return np.hypot(xs[None, :] - pose.x, ys[:, None] - pose.y) <= radius


def handout_border(layers: MapLayers, pose: RoverPose, blind_radius_m: float) -> np.ndarray:
    """Distance to the border of what is mapped, which limits the part of a path handed out. Holes
    inside the map do not cut the path (the planner has made them hazards or costed them), nor does
    the ground the rover stands on and beside it (the sensor's own blind ring)."""
    seen = ~layers.unknown | under_rover(layers.spec, pose, blind_radius_m)
    return distance_to_border(binary_fill_holes(seen), layers.spec.cell)


def look_distance(settings: NavigationSettings, sensor: str) -> float:
    """How far from ground it should look at first the rover stops: outside the sensor's blind ring,
    with the border margin a map needs round what it hands out."""
    return settings.blind_radius_m.of(sensor) + settings.border_margin_m


def hole_mask(layers: MapLayers, start: RoverPose, sensor: str, settings: NavigationSettings) -> np.ndarray:
    """The map's holes that navigation.toml holes makes hazards (none when it keeps them unknown),
    except within the sensor's blind ring round where the rover started mapping: no look could have
    seen that."""
    if settings.holes.of(sensor) == "unknown":
        return np.zeros(layers.spec.shape, bool)
    min_cells = max(1, math.ceil(settings.min_hole_m2 / layers.spec.cell ** 2))
    exempt = under_rover(layers.spec, start, settings.blind_radius_m.of(sensor))
    return enclosed_unknown(layers, min_cells, exempt)


def holes_as_hazards(layers: MapLayers, start: RoverPose, sensor: str, settings: NavigationSettings) -> MapLayers:
    """The map with its holes made hazards where navigation.toml says so (see hole_mask)."""
    holes = hole_mask(layers, start, sensor, settings)
    return with_hazards(layers, holes) if holes.any() else layers


def unlooked_ground(layers: MapLayers, looks: Sequence[tuple[float, float]], here: RoverPose, sensor: str,
                    settings: NavigationSettings) -> np.ndarray:
    """Unknown ground the rover should look at before it drives there (navigation.toml look_first): no
    look (the places the rover mapped from) came within close_look_m of it, beyond the blind ring. What
    stays unknown after such a look is a shadow; and from beside it (the blind ring round the rover)
    no look can see it, so stopping for it would only stall the rover."""
    if not settings.look_first.of(sensor):
        return np.zeros(layers.spec.shape, bool)
    blind = settings.blind_radius_m.of(sensor)
    looked = under_rover(layers.spec, here, blind)
    for x, y in looks:
        looked |= under_rover(layers.spec, RoverPose(x, y), settings.close_look_m) & \
            ~under_rover(layers.spec, RoverPose(x, y), blind)
    return layers.unknown & ~looked


def planning_params(settings: NavigationSettings, weight: float | None, sensor: str) -> PlanningParams:
    return PlanningParams(weight=settings.weight if weight is None else weight,
                          rover_radius_m=settings.rover_radius_m, hazard_margin_m=settings.hazard_margin_m.of(sensor),
                          unknown_policy=settings.unknown_policy, unknown_cost=settings.unknown_cost,
                          max_deviation_m=settings.max_deviation_m, proximity_falloff_m=settings.proximity_falloff_m,
                          proximity_cost=settings.proximity_cost)


def operating_box(server: Host) -> tuple[float, float, float, float] | None:
    """navigation.toml operating_area as (x_min, x_max, y_min, y_max), or None where there is no bound."""
    area = server.settings_of("navigation").operating_area
    if isinstance(area, OperatingArea):
        return area.box
    return server.devices.rover.world_extent() if area == "world" else None


def within_area(layers: MapLayers, box: tuple[float, float, float, float] | None) -> MapLayers:
    """The map with the ground outside the operating area made hazards (they grow like rocks: the
    rover's body stays inside too)."""
    return layers if box is None else with_hazards(layers, outside_box(layers.spec, box))


def check_reach(server: Host, start: tuple[float, float] | None, goal: tuple[float, float]) -> None:
    """Refuse a goal outside the operating area, or farther than the planner's reach (its blank
    global map would be gigabytes); a start given outside the area too."""
    settings: NavigationSettings = server.settings_of("navigation")
    if not all(math.isfinite(v) for v in goal):
        raise BadRequest(f"--to {goal[0]},{goal[1]}: must be finite numbers")
    box = operating_box(server)
    for option, point in (("--from", start), ("--to", goal)):
        if box is not None and point is not None and not inside_box(*point, box):
            raise BadRequest(f"{option} {point[0]:g},{point[1]:g} is outside the operating area: x {box[0]:g}:"
                             f"{box[1]:g}, y {box[2]:g}:{box[3]:g} (navigation.toml operating_area)")
    if start is None:
        pose = server.devices.rover.pose_estimate
        start = (pose.x, pose.y)
    distance = math.dist(start, goal)
    if distance > settings.max_reach_m:
        raise BadRequest(f"--to {goal[0]:g},{goal[1]:g} is {distance:.1f} m from the start; the planner reaches "
                         f"{settings.max_reach_m:g} m (navigation.toml max_reach_m)")


def _validate_plan(server: Host, cfg: PlanPathConfig) -> None:
    check_reach(server, cfg.from_, cfg.to)


@module.job("plan-path", PlanPathConfig, resumable=False, validate=_validate_plan)
def plan_path_command(ctx: JobContext, cfg: PlanPathConfig) -> dict[str, Any]:
    """Plan a safe path on the current maps; cost map, path and waypoints as pictures, JSON and CSV."""
    server = ctx.server
    settings: NavigationSettings = ctx.settings
    pose = server.devices.rover.pose_estimate
    start = cfg.from_ or (pose.x, pose.y)
    ctx.progress(10, f"reading the latest {cfg.sensor} map")
    local, source, folder, extra = local_map(server, cfg.sensor)
    fused = fuse_maps(blank_map_spanning(start, cfg.to, settings.global_cell_m, settings.global_margin_m, [local]),
                      [local])
    fused = within_area(fused, operating_box(server))
    fused = holes_as_hazards(fused, pose, cfg.sensor, settings)
    params = planning_params(settings, cfg.weight, cfg.sensor)
    ctx.progress(30, "planning")
    plan = plan_path(fused, start, cfg.to, params)
    product = ctx.product(cfg, name=cfg.output)
    product.note("inputs", [{"map": source, "path": str(folder)}])
    # On the fused grid: the local map's own grid may not even reach the rover.
    border = handout_border(fused, pose, settings.blind_radius_m.of(cfg.sensor))
    drivable = drivable_prefix(plan.waypoints, fused.spec, border, settings.border_margin_m) if plan.found else None
    ctx.progress(70, "writing")
    write_plan(product, fused, plan, drivable, local, extra["ortho"], start, cfg.to)
    result = ctx.finish_product(product)
    if not plan.found:
        raise BadRequest(f"no path: {plan.reason}: {plan.message}; product={product.name}",
                         data={"product": product.name, "reason": plan.reason})
    return {**result, "waypoints": len(plan.waypoints), "drivable": len(drivable.waypoints),
            "complete": int(drivable.complete), "length": f"{plan.length_m:.2f}", "cost": f"{plan.cost:.3f}",
            "map": source}


def write_plan(product: Any, fused: MapLayers, plan: Any, drivable: Any, local: MapLayers, ortho: np.ndarray,
               start: tuple[float, float], goal: tuple[float, float]) -> None:
    spec = fused.spec
    cost = np.where(plan.hazards.mask, np.nan, plan.cost_grid).astype(np.float32)
    write_geotiff(product.add("cost.tif", "planning cost per cell (NaN: grown hazard)"), cost, spec)
    finite = cost[np.isfinite(cost)]
    high = float(np.percentile(finite, 99)) if finite.size else 1.0
    rgb = colourise(cost, 0.0, high, "viridis")
    rgb[fused.unknown] = (95, 95, 95)
    rgb[plan.hazards.mask] = (200, 50, 40)
    rgb[fused.hazard] = (120, 20, 20)
    picture = draw_path(rgb, spec, plan, drivable, start, goal)
    write_png(product.add("plan.png", "cost map, unknown (grey), grown hazards (red), A* path (white), waypoints, "
                                      "drivable part (cyan)"),
              with_title(with_colour_bar(picture, 0.0, high,
                                         "cost per metre; grey: unknown; red: hazard grown by the rover",
                                         cmap="viridis"), f"{product.name}: plan-path"))
    top = float(np.nanpercentile(ortho, 99)) if np.isfinite(ortho).any() else 1.0
    picture = draw_path(colourise(ortho, 0.0, top, "gray"), local.spec, plan, drivable, start, goal)
    write_png(product.add("plan-ortho.png", "the path on the ortho-image of the local map"),
              with_title(picture, f"{product.name}: path on the ortho-image"))
    rows = [{"index": i, "x": float(x), "y": float(y),
             "drivable": bool(drivable is not None and i < len(drivable.waypoints))}
            for i, (x, y) in enumerate(plan.waypoints)]
    product.write_json("waypoints.json", {"found": plan.found, "reason": plan.reason, "message": plan.message,
                                          "cost": plan.cost if plan.found else None,
                                          "length_m": plan.length_m if plan.found else None,
                                          "waypoints": rows,
                                          "drivable": drivable.waypoints.tolist() if drivable is not None else [],
                                          "frame": "world: x east, y north, metres"},
                       "waypoints in world coordinates, and the drivable prefix")
    with atomic_file(product.add("waypoints.csv", "waypoints: index, x, y, drivable"), "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["index", "x", "y", "drivable"])
        writer.writeheader()
        writer.writerows(rows)


def draw_path(rgb: np.ndarray, spec: GridSpec, plan: Any, drivable: Any, start, goal) -> np.ndarray:
    """The path, waypoints, start and goal drawn on a grid picture (north up, enlarged)."""
    canvas = Canvas(rgb, spec, 600)
    if plan.found and len(plan.cells):
        canvas.line(cells_to_world(spec, plan.cells), (255, 255, 255), 1, antialiased=False)
        for point in plan.waypoints:
            cv2.circle(canvas.image, canvas.pixel(point), 3, (255, 210, 0), -1)
        if drivable is not None:
            canvas.line(drivable.waypoints, (0, 230, 255), 2, antialiased=False)
    cv2.circle(canvas.image, canvas.pixel(start), 5, (0, 255, 0), 2)
    cv2.drawMarker(canvas.image, canvas.pixel(goal), (255, 0, 255), cv2.MARKER_CROSS, 12, 2)
    return canvas.image


@module.immediate("pose", PoseConfig, positionals=("pose",))
def pose(call: Call, cfg: PoseConfig) -> dict[str, Any]:
    """The rover's pose from the GNC: X,Y,HEADING (metres, metres, degrees CCW from east).

    Answered at once even while a job runs: navigate waits for it after handing out waypoints."""
    parts = cfg.pose.split(",")
    try:
        x, y, heading = (float(p) for p in parts)
    except ValueError:
        raise BadRequest(f"pose: {cfg.pose!r} is not X,Y,HEADING (three numbers)") from None
    if not all(math.isfinite(v) for v in (x, y, heading)):
        raise BadRequest(f"pose: {cfg.pose!r} must be finite numbers")
    rover = call.server.devices.rover
    old = rover.pose_estimate
    reported = RoverPose(x, y, old.z, math.radians(heading), old.roll, old.pitch)
    rover.report_pose(rover.settle(reported, ground=lambda: newest_dem(call.server)))
    return {"x": f"{x:.3f}", "y": f"{y:.3f}", "heading": f"{heading:.2f}"}


def newest_dem(server: Host) -> tuple[np.ndarray, GridSpec] | None:
    """The heights and grid of the newest DEM product of either sensor, or None: the terrain under
    the wheels that gives a rover without an inclinometer its attitude after the GNC moved it."""
    mapped = server.products.latest("dem-.*")
    if mapped is None or not (mapped.path / "dem.tif").exists():
        return None
    heights, spec = read_geotiff(mapped.path / "dem.tif")
    return heights, spec
