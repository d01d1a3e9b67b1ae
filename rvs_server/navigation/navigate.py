"""navigate: map, localise, plan, drive, and again, until the rover stands at the goal.

The thesis' navigation (sections 4.4, 5.4-5.5) mapped once, planned once and drove, with the rover
placed where odometry said. Here each cycle

  1. looks along the heading with the sensor (orient, navigation.toml `orient`): visual odometry
     since the last cycle's look and the sun's heading replace dead reckoning's estimate;
     then maps the surroundings with the sensor (workflows/navigate-<sensor>.yaml), aligning the new
     points to the map of the earlier cycles first: the alignment corrects the pose;
  2. stops if the corrected position is within the tolerance of the goal;
  3. plans on a blank global map spanning rover and goal fused with every cycle's local map, and
     keeps the last cycle's route while it stays clear and near the new plan's cost (a rover that
     re-chose after every look would swing between near-equal ways round);
  4. hands out the part of the path inside the newest map and a margin from its border, at most
     max_drive_m long and short of where the drive error could take the rover's body onto a
     hazard (toolbox planning_drive_error): the rover device's drive takes it (rvs_server/devices/rover.py,
     navigation.toml drive): in the simulation the rover drives it (turn, then straight, with drive
     error); with a real rover the waypoints go out as a `navigate` event and the job waits for the
     GNC's `pose X,Y,HEADING`.

The state of the traverse is checkpointed after the mapping of each cycle and after each waypoint,
so `break` stops within a cycle (at a view, a step or a waypoint) and `continue` carries on there.
The product holds every cycle's maps and plan (cycle-NN/), the driven path (estimated, dead
reckoning and, simulated, true) and an overview of the whole traverse.
"""
from __future__ import annotations

import csv
import math
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
from pydantic import Field
from scipy.ndimage import distance_transform_edt

from rvs_server.config import CommandConfig, Point, SafeName
from rvs_server.devices.rover import DriveStopped, Moved, Pace, WorldEdge, dead_reckon, turn_and_distance
from rvs_server.files import atomic_file, save_npy_atomic
from rvs_server.jobs import JobContext
from rvs_server.mapping import (
    MappingSettings,
    WorkflowArgs,
    check_workflow,
    fusion_record,
    leave_camera_as_acquired,
    operations,
    write_maps,
)
from rvs_server.navigation.commands import (
    NavigationSettings,
    check_reach,
    handout_border,
    hole_mask,
    look_distance,
    module,
    operating_box,
    planning_layers,
    planning_params,
    under_rover,
    unlooked_ground,
    within_area,
    write_plan,
)
from rvs_server.navigation.pictures import write_traverse
from rvs_server.orientation import OrientFailed, OrientSettings, odometer_of, orient_here
from rvs_server.products.manifests import ProductPart
from rvs_server.products.rasters import read_geotiff
from rvs_server.protocol import BadRequest
from rvs_server.workflow import WorkflowError, resolve_params, run_workflow
from toolbox.geometry import RoverPose
from toolbox.grid import GridSpec
from toolbox.mapping import hazard as hazard_codes
from toolbox.mapping.localisation import merge_clouds
from toolbox.planning import (
    DrivablePrefix,
    MapLayers,
    PlanningParams,
    PlanResult,
    blank_map_spanning,
    drivable_prefix,
    fuse_nearest,
    hazards_onto,
    holes_on_path,
    keep_route,
    nearest_open_cell,
    outside_box,
    plan_path,
    plan_through_unconfirmed,
    short_of_first_touch,
    with_hazards,
    with_unknown,
)
from toolbox.planning.drive_error import cut_for_drive_error
from toolbox.planning.paths import path_length

if TYPE_CHECKING:
    from rvs_server.host import Host

SENSOR_DEVICES = {"tof": ("tof",), "stereo": ("cameras",), "fused": ("tof", "cameras")}
ORIENT_SENSOR = {"tof": "tof", "stereo": "stereo", "fused": "tof"}   # fused: orient with the precise one
MAP_CLOUD_VOXEL_M = 0.05


class NavigateConfig(CommandConfig):
    to: Point = Field(..., description="goal X,Y in the world frame, metres")
    sensor: Literal["tof", "stereo", "fused"] = Field("tof", description="which sensor maps the way (fused: both, "
                                                     "workflows/navigate-fused.yaml)")
    tolerance: float = Field(0.3, gt=0, le=10, description="arrived when the estimated position is this close, metres")
    max_steps: int = Field(12, ge=1, le=100, description="cycles of map, plan and drive at most; after the last "
                           "drive the rover maps once more to see whether it arrived")
    weight: float | None = Field(None, ge=0, le=1, description="distance weight w; default navigation.toml")
    output: SafeName | None = Field(None, description="product name; default navigate-TIME")


@dataclass
class Traverse:
    """What navigate knows between cycles; checkpointed as a dict."""

    product: str
    start: list[float]
    cycle: int = 0                       # cycles begun
    phase: str = "map"                   # map: the next thing is mapping; drive: waypoints remain
    pose: list[float] = field(default_factory=list)       # estimate: x, y, z, heading, roll, pitch
    odometry: list[float] = field(default_factory=list)   # dead reckoning alone: x, y, heading
    estimated_path: list[list[float]] = field(default_factory=list)
    odometry_path: list[list[float]] = field(default_factory=list)
    true_path: list[list[float]] = field(default_factory=list)
    to_drive: list[list[float]] = field(default_factory=list)
    route: list[list[float]] = field(default_factory=list)  # the last plan's waypoints, kept while good enough
    route_aim: list[float] = field(default_factory=list)
    cycles: list[dict[str, Any]] = field(default_factory=list)
    contacts: int = 0
    stalls: int = 0
    hazard_stops: int = 0                # drives the hazard guard stopped short of a hazard (hazard-start)
    orients: list[dict[str, Any]] = field(default_factory=list)   # each cycle's orient look (navigation.toml orient)
    moved: list[float] = field(default_factory=lambda: [0.0, 0.0])  # metres, degrees since the last fix
    best_percent: float = 0.0
    tof_exposure: int = -1               # the SR4000's exposure as the last panorama left it (-1: none yet)

    @property
    def rover(self) -> RoverPose:
        return RoverPose(*self.pose)


class NavigateArgs(WorkflowArgs):
    """$args of navigate's mapping workflows: the view ranges, and the map to localise against."""

    reference: str = ""
    max_translation_m: float = Field(1.0, gt=0)
    max_rotation_deg: float = Field(10.0, gt=0, le=90)
    step_limit: float = Field(0.10, gt=0)


def _validate(server: Host, cfg: NavigateConfig) -> None:
    for device in SENSOR_DEVICES[cfg.sensor]:
        server.devices[device].require_healthy()
    check_workflow(server, f"navigate-{cfg.sensor}", NavigateArgs)
    check_reach(server, None, cfg.to)


@module.job("navigate", NavigateConfig, devices=("ptu",), validate=_validate)
def navigate(ctx: JobContext, cfg: NavigateConfig) -> dict[str, Any]:
    """Map, localise, plan and drive in cycles until the rover is within tolerance of the goal."""
    return Navigation(ctx, cfg).run()


class FusedMaps(NamedTuple):
    seen: MapLayers           # every cycle's map fused
    unconfirmed: np.ndarray   # hazards until a close look clears them: holes (stereo), hazards seen from afar
    unlooked: np.ndarray      # unknown ground to look at before driving there (navigation.toml look_first)
    newest: MapLayers


class Handout(NamedTuple):
    drivable: DrivablePrefix | None
    error_m: float            # the drive error where it cut the drive; 0: it did not
    to_look: bool             # cut short of unknown ground the path crosses, to look at it first


class CycleJob:
    """The job as a cycle's workflow sees it: progress messages name the cycle, the percent stays
    the traverse's."""

    def __init__(self, ctx: JobContext, cycle: int, percent: float):
        self._ctx, self._cycle, self._percent = ctx, cycle, percent

    def progress(self, percent: float, message: str) -> None:
        self._ctx.progress(self._percent, f"cycle {self._cycle}: mapping: {message}")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ctx, name)


class Navigation:
    def __init__(self, ctx: JobContext, cfg: NavigateConfig):
        self.ctx, self.cfg = ctx, cfg
        self.server = ctx.server
        self.settings: NavigationSettings = ctx.settings
        self.mapping: MappingSettings = ctx.settings_of("mapping")
        self.product = ctx.product(cfg, name=cfg.output)
        self.goal = (float(cfg.to[0]), float(cfg.to[1]))
        self.rover = ctx.devices.rover
        self.drive_by = self.rover.drive(self.settings.drive, "navigation.drive")
        self.orient_settings: OrientSettings = ctx.settings_of("orientation")
        # A GNC's pose is the estimate: nothing to orient between.
        self.orienting = self.settings.orient.of(cfg.sensor) and self.drive_by.simulated
        resume = ctx.resume or {}
        if "traverse" in resume:
            self.state = Traverse(**resume["traverse"])
            self.rover.pose_estimate = self.state.rover
            if self.state.tof_exposure >= 0:
                # The restart reopened the SR4000 at its configured exposure; the next panorama's first
                # view must start from the one the last panorama left, as in an uninterrupted run.
                ctx.devices.tof.require().set_integration_time(self.state.tof_exposure)
            if self.state.true_path:   # a restarted simulated world has the rover at its start
                self.drive_by.resume_at(*self.state.true_path[-1][:3])
        else:
            pose = self.rover.pose_estimate
            self.state = Traverse(product=self.product.name, start=[pose.x, pose.y],
                                  pose=[pose.x, pose.y, pose.z, pose.heading, pose.roll, pose.pitch],
                                  odometry=[pose.x, pose.y, pose.heading])
            self._record_position()
        self.start_distance = math.dist(self.state.start, self.goal)

    # ---------------------------------------------------------------------------------- the loop
    def run(self) -> dict[str, Any]:
        state = self.state
        while True:
            if state.phase == "drive":
                self.drive()
                state.phase = "map"
                self.checkpoint()
            state.cycle += 1
            self.map_cycle()
            if self.distance_to_goal() <= self.cfg.tolerance:
                return self.finish()
            # After the last drive the rover still maps once more: only a fresh look says whether it arrived.
            if state.cycle > self.cfg.max_steps:
                self.fail("max_steps", f"not at the goal after {self.cfg.max_steps} cycles (--max-steps): "
                          f"{self.distance_to_goal():.2f} m to go")
            self.plan_cycle()
            self.checkpoint()

    def orient_look(self) -> None:
        """Visual odometry since the last cycle's look (rvs_server/orientation): the estimate the
        map alignment starts from. A look that cannot be matched leaves dead reckoning's."""
        state, sensor = self.state, self.cfg.sensor
        self.progress(f"cycle {state.cycle}: orienting along the heading")
        record: dict[str, Any]
        self.rover.pose_estimate = state.rover
        try:
            outcome = orient_here(self.ctx, ORIENT_SENSOR[sensor], self.orient_settings)
        except OrientFailed as failed:
            record = {"failed": failed.failure.reason, "sentence": failed.failure.sentence}
        else:
            pose = outcome.belief.pose
            state.pose = [pose.x, pose.y, state.pose[2], pose.heading, pose.roll, pose.pitch]
            sigma_xy, sigma_heading = outcome.belief.sigmas()
            record = {"keyframe": outcome.keyframe, "sources": outcome.sources, "x": pose.x, "y": pose.y,
                      "heading_deg": math.degrees(pose.heading), "sigma_xy_m": sigma_xy,
                      "sigma_heading_deg": math.degrees(sigma_heading),
                      "inliers": outcome.motion.inliers if outcome.motion is not None else 0}
        state.orients.append({"cycle": state.cycle, **record})
        self.rover.pose_estimate = state.rover
        if state.estimated_path:
            state.estimated_path[-1] = [state.pose[0], state.pose[1], state.pose[3]]

    def map_cycle(self) -> None:
        state, cycle = self.state, self.state.cycle
        if self.orienting:
            self.orient_look()
        full = cycle == 1 or state.stalls > 0
        pan = self.settings.first_pan if full else self.settings.cycle_pan
        self.progress(f"cycle {cycle}: mapping (pan {pan[0]:g}:{pan[1]:g})")
        command = f"navigate-{self.cfg.sensor}"
        workflow = check_workflow(self.server, command, NavigateArgs)
        tilt = self.settings.tilt.of(self.cfg.sensor)
        reference = self._map_cloud_path(cycle - 1)
        metres, degrees = state.moved
        # How far odometry can be off since the last map: the alignment believes no more than this.
        args = NavigateArgs(pan=pan, tilt=tilt,
                            cell=self.mapping.cell, overlap=self.mapping.overlap,
                            reference=str(reference) if reference is not None else "",
                            max_translation_m=0.3 + 0.15 * metres,
                            max_rotation_deg=min(90.0, 3.0 + 0.1 * degrees + 1.5 * metres),
                            step_limit=self.settings.step_limit_m)
        try:
            params = resolve_params(workflow, operations, args, self.mapping)
        except WorkflowError as exc:
            raise BadRequest(f"navigate: {exc}") from None
        before = state.rover
        self.rover.pose_estimate = before
        working = self.server.recovery.folder(self.ctx.job.id)
        forget_finished_cycles(working, cycle)
        folder = working / f"cycle-{cycle:02d}"
        results, provenance = run_workflow(workflow, operations, params, CycleJob(self.ctx, cycle, state.best_percent),
                                           folder)
        for acquisition in ("acquired_tof", "acquired"):      # navigate-fused has both
            acquired = results.get(acquisition) or {}
            leave_camera_as_acquired(self.ctx, acquired)
            if acquired.get("sensor") == "tof" and int(acquired.get("integration_time", -1)) >= 0:
                state.tof_exposure = int(acquired["integration_time"])
        aligned = results["aligned"]
        after = RoverPose.from_matrix(np.asarray(aligned["correction"]) @ before.to_world())
        if self.orienting and aligned["accepted"]:   # the odometer's chain follows the map's correction
            odometer_of(self.server).shift(np.asarray(aligned["correction"]))
        state.pose = [after.x, after.y, after.z, after.heading, after.roll, after.pitch]
        self.rover.pose_estimate = after
        part = ProductPart(self.product, f"cycle-{cycle:02d}")
        summary = write_maps(self.ctx, part, results, self.mapping)
        self.ctx.save_truth(part)
        previous = np.load(reference) if reference is not None else None
        # A view that could not be aligned stays out of the map it would blur; it still serves as
        # this cycle's local map, which is consistent with where the rover believes it is.
        added = aligned["points"] if previous is None or aligned["accepted"] else np.empty((0, 3), np.float32)
        save_npy_atomic(part.add("map-cloud.npy", "the map's cloud after this cycle (world frame, 5 cm voxels; the "
                                 "next cycle aligns to it)"), merge_clouds(previous, added, MAP_CLOUD_VOXEL_M))
        if aligned["accepted"]:  # until one is, odometry's uncertainty keeps growing
            state.moved = [0.0, 0.0]
        record = {"cycle": cycle, "pose_odometry": _pose_list(before), "pose_corrected": _pose_list(after),
                  "alignment": {k: (float(aligned[k]) if k not in ("accepted", "reason") else aligned[k])
                                for k in ("accepted", "reason", "dx", "dy", "dz", "dyaw", "fitness", "rmse",
                                          "constraint")},
                  "map": summary, "pan": list(args.pan), "steps": [p["step"] for p in provenance]}
        fusion = fusion_record(results)      # navigate-fused: the stereo bias against the TOF, and the counts
        if fusion is not None:
            record["fusion"] = fusion
        true = self.drive_by.true_pose()
        if true is not None:
            record["pose_true"] = true
        state.cycles.append(record)
        if state.estimated_path:
            state.estimated_path[-1] = [after.x, after.y, after.heading]

    def plan_cycle(self) -> None:
        state, cycle = self.state, self.state.cycle
        self.progress(f"cycle {cycle}: planning, {self.distance_to_goal():.2f} m to go")
        seen, unconfirmed, unlooked, newest = self.fused_map()
        fused = closed_map = with_hazards(seen, unconfirmed)
        start = (state.pose[0], state.pose[1])
        params = planning_params(self.settings, self.cfg.weight, self.cfg.sensor)
        plan = plan_path(fused, start, self.goal, params)
        aim = self.goal
        if plan.reason == "goal_blocked":
            # Too close to a rock for the rover's centre, but arriving within the tolerance will do.
            near = nearest_open_cell(plan.cost_grid, fused.spec, self.goal, self.cfg.tolerance - fused.spec.cell,
                                     start)
            if near is not None:
                aim = near
                plan = plan_path(fused, start, aim, params)
            elif self.distance_to_goal() > self.settings.confirm_range_m:
                # Seen from afar (a few noisy pixels): go and look from close by before refusing.
                plan = plan_path(unseen_near(fused, self.goal, self.settings.confirm_range_m / 2), start, aim, params)
        closed = plan
        open_map = with_unknown(seen, unconfirmed)
        plan, look_m = self.look_again(plan, open_map, unconfirmed, unlooked, start, aim, params)
        if look_m is not None:
            fused = open_map
        elif state.route and math.dist(state.route_aim, aim) < 1e-6:
            plan = keep_route(plan, np.array(state.route), start, fused.spec, params, self.settings.route_hysteresis)
        if plan.found:
            state.route, state.route_aim = plan.waypoints.tolist(), list(aim)
        drivable, error_m, to_look = self.handout(plan, fused, unconfirmed, unlooked, look_m, params)
        part = ProductPart(self.product, f"cycle-{cycle:02d}")
        ortho_path = self.product.path / f"cycle-{cycle:02d}" / "ortho.tif"
        ortho = read_geotiff(ortho_path)[0] if ortho_path.exists() else np.full(newest.spec.shape, np.nan)
        write_plan(part, fused, plan, drivable, newest, ortho, start, aim)
        record = state.cycles[-1]
        record["plan"] = {"found": plan.found, "reason": plan.reason, "aim": list(aim), "kept": plan.kept,
                          "length_m": plan.length_m if plan.found else None, "through_unconfirmed": look_m is not None}
        if not plan.found:
            self.fail(plan.reason, plan.message, fused=fused)
        route = clip_length(drivable.waypoints, self.max_drive_m)
        record["drive"] = route.tolist()
        if error_m > 0:
            record["drive_error_cut_m"] = error_m
            self.progress(f"cycle {cycle}: driving {path_length(route):.2f} m and mapping again: farther, the drive "
                          f"error ({100 * error_m:.0f} cm at {self.settings.drive_error_sigmas:g} sigma) would take "
                          "more than the room the path keeps from the hazards")
        elif to_look:
            record["looks_first"] = True
            self.progress(f"cycle {cycle}: driving {path_length(route):.2f} m and mapping again: the path crosses "
                          f"ground no look has seen (a shadow, or beyond the map), to look at from {self.look_m:.1f} "
                          "m first")
        if look_m is not None and path_length(route) < self.settings.min_progress_m:
            self.fail(closed.reason, f"{closed.message}; the ways that are left cross ground no close look has "
                      f"confirmed, looked at from {look_m:.1f} m already", fused=closed_map)
        # The last short step onto the aim is progress, not a stall (a blocked goal's aim may lie 10 cm off).
        last_step = drivable.complete and path_length(route) > 0 and math.dist(route[-1], aim) < fused.spec.cell
        if path_length(route) < self.settings.min_progress_m and not last_step:
            state.stalls += 1
            if state.stalls > 1:
                self.fail("stuck", "the safe part of the path inside the map stays too short to drive "
                          f"({path_length(route):.2f} m) even after a full panorama", fused=fused)
            return
        state.stalls = 0
        state.to_drive = waypoints_from(state.pose[:2], route[1:].tolist())
        state.phase = "drive"

    def look_again(self, closed: PlanResult, open_map: MapLayers, unconfirmed: np.ndarray, unlooked: np.ndarray,
                   start: tuple[float, float], aim: tuple[float, float],
                   params: PlanningParams) -> tuple[PlanResult, float | None]:
        """When ground no close look has confirmed (holes; hazards seen only from beyond confirm_range_m)
        closes every way or makes a long detour: the plan through it, and how far from it the rover stops
        to look again, outside its blind ring. Far hazards are often range noise and holes often
        shadows; a close look clears them or confirms a rock. Otherwise the plan as it was, and None."""
        through = (plan_through_unconfirmed(closed, open_map, start, aim, params, self.settings.look_again_detour)
                   if unconfirmed.any() else None)
        if through is None:
            return closed, None
        look_m = self.look_m
        if closed.found and self.drive_length(self.handout(through, open_map, unconfirmed, unlooked, look_m,
                                                           params).drivable) < self.settings.min_progress_m:
            return closed, None       # already as close as a look needs to be, and it did not clear the way
        why = ("every way crosses" if not closed.found else
               f"the way round ({closed.length_m:.1f} m) is much longer than the way through")
        self.progress(f"cycle {self.state.cycle}: {why} ground no close look has confirmed; going to look at it "
                      f"from {look_m:.1f} m")
        return through, look_m

    def handout(self, plan: PlanResult, layers: MapLayers, unconfirmed: np.ndarray, unlooked: np.ndarray,
                look_m: float | None, params: PlanningParams) -> Handout:
        """The part of the plan to drive: inside what the cycles have mapped, a margin from its border,
        when it goes to look again short of the unconfirmed ground it crosses, short of the first unknown
        ground it crosses that no look has seen from close by, and short of where the drive error could
        take the body onto a hazard."""
        if not plan.found:
            return Handout(None, 0.0, False)
        border = handout_border(layers, self.state.rover, self.settings.blind_radius_m.of(self.cfg.sensor))
        drivable = drivable_prefix(plan.waypoints, layers.spec, border, self.settings.border_margin_m)
        if look_m is not None:
            drivable = short_of_unconfirmed(drivable, plan, unconfirmed, layers.spec, params.clearance_m, look_m)
        looked, to_look = short_of_first_touch(drivable, plan.cells, unlooked, layers.spec, params.clearance_m,
                                               self.look_m)
        # A cut beyond the longest drive changes nothing this cycle.
        to_look = to_look and self.drive_length(looked) < self.drive_length(drivable) - 1e-6
        return Handout(*self.short_of_drive_error(looked, plan, layers.spec), to_look)

    def short_of_drive_error(self, drivable: DrivablePrefix, plan: PlanResult,
                             spec: GridSpec) -> tuple[DrivablePrefix, float]:
        settings = self.settings
        cut, error_m = cut_for_drive_error(clip_length(drivable.waypoints, self.max_drive_m),
                                           self.state.rover.heading, plan.hazards.distance_m, spec,
                                           settings.footprint_m, settings.drive_error, settings.drive_error_sigmas,
                                           min_drive_m=settings.min_progress_m + spec.cell)   # never a stall
        return (drivable, 0.0) if cut.complete else (cut, error_m)

    @property
    def max_drive_m(self) -> float:
        return self.settings.max_drive_m.of(self.cfg.sensor)

    @property
    def look_m(self) -> float:
        return look_distance(self.settings, self.cfg.sensor)

    def drive_length(self, drivable: DrivablePrefix | None) -> float:
        return 0.0 if drivable is None else path_length(clip_length(drivable.waypoints, self.max_drive_m))

    # ---------------------------------------------------------------------------------- the maps
    def fused_map(self) -> FusedMaps:
        """Every cycle's map over a blank global map spanning rover and goal, each cell as seen from
        the nearest place the rover mapped from (a close look corrects a far one); the rover's own
        footprint is safe ground. Also what no close look has confirmed: the holes no look filled
        that navigation.toml makes hazards, and (navigation.toml far_hazards) hazards seen only from
        beyond confirm_range_m; the unknown ground to look at before driving there; and the newest map."""
        rover = self.state.rover
        maps = [planning_layers(self.product.path / f"cycle-{c['cycle']:02d}", self.settings, rover)
                for c in self.state.cycles]
        blank = blank_map_spanning((rover.x, rover.y), self.goal, self.settings.global_cell_m,
                                   self.settings.global_margin_m, maps)
        nearest = fuse_nearest(blank, maps, [c["pose_corrected"][:2] for c in self.state.cycles],
                               self.settings.sticky_range_m)
        box = operating_box(self.server)
        fused = within_area(nearest, box)
        under = under_rover(fused.spec, rover, self.settings.rover_radius_m)
        cost = np.where(under, np.where(np.isfinite(fused.cost), fused.cost, 0.0), fused.cost)
        fused = MapLayers(fused.spec, np.where(under & fused.hazard, 0.0, cost), fused.hazard & ~under,
                          fused.unknown & ~under)
        # What the hazard guard saw while driving (a rock dropped, a person) stays a hazard for the plan,
        # also where this cycle's partial scan did not look.
        guarded = self.guard_hazards(fused.spec) & ~under
        fused = with_hazards(fused, guarded)
        self.state.cycles[-1]["guard_hazard_cells"] = int(guarded.sum())
        far = np.zeros(fused.spec.shape, bool)
        if self.settings.far_hazards.of(self.cfg.sensor) == "unconfirmed":
            far = nearest.hazard & fused.hazard & (nearest.seen_from > self.settings.confirm_range_m)
            if box is not None:
                far &= ~outside_box(fused.spec, box)     # the operating area's edge is no sensor's guess
        start = RoverPose(*self.state.cycles[0]["pose_corrected"])
        looks = [c["pose_corrected"][:2] for c in self.state.cycles]
        # A hole is walled in by seen ground: unexplored ground along the operating area's edge is none.
        in_area = fused if box is None else with_unknown(fused, outside_box(fused.spec, box))
        holes = hole_mask(in_area, start, self.cfg.sensor, self.settings)
        unlooked = unlooked_ground(fused, looks, rover, self.cfg.sensor, self.settings)
        return FusedMaps(fused, holes | far, unlooked, maps[-1])

    def guard_hazards(self, spec: GridSpec) -> np.ndarray:
        """The hazards in the running hazard activity's memory (hazard-start) on `spec`; none without one."""
        activity = self.server.activities.running("hazard")
        memory = getattr(activity, "memory", None)
        if memory is None:
            return np.zeros(spec.shape, dtype=bool)
        source, code = memory.snapshot()
        if source is None:
            return np.zeros(spec.shape, dtype=bool)
        return hazards_onto(spec, source, hazard_codes.is_hazard(code))

    def _map_cloud_path(self, cycle: int):
        if cycle < 1:
            return None
        path = self.product.path / f"cycle-{cycle:02d}" / "map-cloud.npy"
        return path if path.exists() else None

    # ---------------------------------------------------------------------------------- driving
    def drive(self) -> None:
        """Drive the waypoints handed out (the rover device's drive: simulated, or the GNC's, which
        the job waits for; the wait ends at `break` too), checkpointed after each part."""
        state, settings = self.state, self.settings
        pace = Pace(self.mapping.truth_step, settings.pose_timeout_s)
        try:
            if self.orienting:
                self.drive_looking(pace)
                return
            moves = self.drive_by.waypoints(self.ctx, state.to_drive, state.rover, pace, self.goal, state.cycle,
                                            self._announce_leg)
            for moved in moves:
                if moved.commanded is None:
                    self._driven_by_gnc(moved)
                else:
                    self._driven(moved)
        except WorldEdge as exc:
            self.fail("world_edge", str(exc))
        except DriveStopped as exc:
            # The hazard guard saw what the maps did not (a rock dropped, a person): keep the part driven,
            # drop the rest of the hand-out, and map again from here to plan round it.
            self._driven(exc.moved, legs=0)
            state.to_drive = []
            state.hazard_stops += 1
            state.cycles[-1]["hazard_stop"] = exc.sentence
            self.progress(f"cycle {state.cycle}: {exc.message}; mapping again to plan round it")

    def drive_looking(self, pace: Pace) -> None:
        """With orient: the legs cut into parts of at most orient_step_m and driven one by one, with
        an orient look whenever the next part would take the rover more than orient_step_m from the
        last look (a plan's short legs share one; the next cycle's look ends the drive), and a turn
        the sensor's view could not bridge made first, in parts of at most orient_turn_deg with a
        look after each; each part aims from where the last look put the rover."""
        state, settings = self.state, self.settings
        state.to_drive = pieces(state.pose[:2], state.to_drive, settings.orient_step_m)
        since = 0.0      # metres driven since the last look: a plan's short legs share one
        while state.to_drive:
            target = state.to_drive[0]
            turn, distance = turn_and_distance((state.pose[0], state.pose[1], state.pose[3]), target)
            parts = math.ceil(abs(math.degrees(turn)) / settings.orient_turn_deg - 1e-9)
            if parts > 1 and since > 0:     # the view before the turn, to turn from
                self.orient_look()
            for _ in range(parts if parts > 1 else 0):
                self._driven(self.drive_by.act(self.ctx, "turn", turn / parts, pace), legs=0)
                self.orient_look()
                since = 0.0
            if since + distance > settings.orient_step_m + 1e-6:   # this leg would outrun the step
                self.orient_look()
                since = 0.0
            moves = self.drive_by.waypoints(self.ctx, [target], state.rover, pace, self.goal, state.cycle,
                                            self._announce_leg)
            self._driven(next(iter(moves)))
            since += distance
            self.checkpoint()

    def _announce_leg(self, target: Sequence[float] | None) -> None:
        state = self.state
        if target is None:
            self.progress(f"cycle {state.cycle}: waiting for the GNC to drive {len(state.to_drive)} waypoints and "
                          f"send pose X,Y,HEADING")
        else:
            self.progress(f"cycle {state.cycle}: driving to ({target[0]:.2f}, {target[1]:.2f}), "
                          f"{self.distance_to_goal():.2f} m to go")

    def _driven(self, moved: Moved, legs: int | None = None) -> None:
        """A leg the simulated rover drove (legs: the waypoints it reached, default moved.legs): the
        estimate dead-reckoned, standing on the newest DEM."""
        state = self.state
        turn, distance = moved.commanded
        rover, pose = state.rover, moved.estimate
        ox, oy, oh = dead_reckon(tuple(state.odometry), turn, distance)
        state.pose = [pose.x, pose.y, self._ground_height(pose.x, pose.y, rover.z), pose.heading, pose.roll,
                      pose.pitch]
        state.odometry = [ox, oy, oh]
        state.contacts += moved.contacts
        state.moved = [state.moved[0] + abs(distance), state.moved[1] + abs(math.degrees(turn))]
        state.true_path.extend(moved.true_path)
        del state.to_drive[:moved.legs if legs is None else legs]
        self.rover.pose_estimate = state.rover
        self._record_position(true=False)
        self.checkpoint()

    def _driven_by_gnc(self, moved: Moved) -> None:
        """The GNC drove the waypoints: its pose is the estimate, and odometry starts from it."""
        state, pose = self.state, moved.estimate
        state.pose = [pose.x, pose.y, pose.z, pose.heading, pose.roll, pose.pitch]
        state.odometry = [pose.x, pose.y, pose.heading]
        del state.to_drive[:moved.legs]
        self._record_position(true=False)

    def _ground_height(self, x: float, y: float, fallback: float) -> float:
        """The newest DEM's median height within the rover's radius of (x, y): where the rover stands."""
        if not self.state.cycles:
            return fallback
        heights, spec = read_geotiff(self.product.path / f"cycle-{self.state.cycles[-1]['cycle']:02d}" / "dem.tif")
        near = under_rover(spec, RoverPose(x, y), self.settings.rover_radius_m) & np.isfinite(heights)
        return float(np.median(heights[near])) if near.any() else fallback

    # ---------------------------------------------------------------------------------- bookkeeping
    def _record_position(self, true: bool = True) -> None:
        state = self.state
        state.estimated_path.append([state.pose[0], state.pose[1], state.pose[3]])
        state.odometry_path.append(list(state.odometry))
        if true and not state.true_path and (pose := self.drive_by.true_pose()) is not None:
            state.true_path.append(pose)

    def distance_to_goal(self) -> float:
        return math.dist(self.state.pose[:2], self.goal)

    def progress(self, message: str) -> None:
        done = 1.0 - self.distance_to_goal() / max(self.start_distance, 1e-9)
        self.state.best_percent = max(self.state.best_percent, min(99.0, 100.0 * done))
        self.ctx.progress(self.state.best_percent, message)

    def checkpoint(self) -> None:
        self.ctx.checkpoint({"product": self.product.name, "traverse": asdict(self.state)})

    def finish(self) -> dict[str, Any]:
        state = self.state
        self.write_traverse("arrived", "")
        result = self.ctx.finish_product(self.product)
        pose = state.rover
        return {**result, "cycles": state.cycle, "x": f"{pose.x:.3f}", "y": f"{pose.y:.3f}",
                "heading": f"{math.degrees(pose.heading):.2f}", "remaining": f"{self.distance_to_goal():.3f}",
                "driven": f"{path_length(np.array(state.estimated_path)[:, :2]):.2f}"}

    def fail(self, reason: str, message: str, fused: MapLayers | None = None) -> None:
        self.write_traverse(reason, message, fused)
        raise BadRequest(f"navigate stopped: {reason}: {message}; product={self.product.name}",
                         data={"product": self.product.name, "reason": reason, "cycles": self.state.cycle})

    def write_traverse(self, outcome: str, message: str, fused: MapLayers | None = None) -> None:
        state = self.state
        if fused is None and state.cycles:
            maps = self.fused_map()
            fused = with_hazards(maps.seen, maps.unconfirmed)
        truth = None
        pose = self.drive_by.true_pose()
        if pose is not None:
            truth = {"path": state.true_path, "contacts": state.contacts, "pose": pose,
                     "step_height_m": self.mapping.truth_step}
        write_traverse(self.ctx, self.product, state, self.goal, outcome, message, fused, truth)
        with atomic_file(self.product.add("path.csv", "the driven path: estimated (map-corrected) and dead reckoning"),
                         "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["index", "x", "y", "heading_deg", "odometry_x", "odometry_y", "odometry_heading_deg"])
            for i, (est, odo) in enumerate(zip(state.estimated_path, state.odometry_path, strict=True)):
                writer.writerow([i, f"{est[0]:.4f}", f"{est[1]:.4f}", f"{math.degrees(est[2]):.3f}",
                                 f"{odo[0]:.4f}", f"{odo[1]:.4f}", f"{math.degrees(odo[2]):.3f}"])


def forget_finished_cycles(working: Path, cycle: int) -> None:
    """Delete the workflow checkpoints of the cycles before this one. Their maps are in the product and
    a resumed traverse never maps them again; kept, a stereo cycle's 400 MB (views, clouds) each filled
    the disk within a 25-cycle traverse."""
    for folder in working.glob("cycle-*"):
        if int(folder.name.removeprefix("cycle-")) < cycle:
            shutil.rmtree(folder, ignore_errors=True)


def short_of_unconfirmed(drivable: DrivablePrefix, plan: PlanResult, unconfirmed: np.ndarray, spec: GridSpec,
                         clearance_m: float, look_m: float) -> DrivablePrefix:
    """The drivable part cut where it first comes within look_m of the unconfirmed ground the plan crosses."""
    crossed = holes_on_path(plan.cells, unconfirmed, spec.cell, clearance_m)
    if not crossed.any():
        return drivable
    return drivable_prefix(drivable.waypoints, spec, distance_transform_edt(~crossed) * spec.cell, look_m)


def unseen_near(layers: MapLayers, point: tuple[float, float], radius: float) -> MapLayers:
    """The map with everything within radius of a point made unknown again."""
    return with_unknown(layers, under_rover(layers.spec, RoverPose(*point), radius))


MIN_LEG_M = 0.05     # a first waypoint nearer than this is where the rover stands (its cell's centre)


def waypoints_from(here: Sequence[float], waypoints: list[list[float]]) -> list[list[float]]:
    """The waypoints without the leading ones within MIN_LEG_M of here (the last one stays): turning
    toward a point 2 cm away points the rover anywhere (the tests' navigate turned 88 deg, drove
    2 cm, and turned 148 deg back)."""
    out = list(waypoints)
    while len(out) > 1 and math.dist(here[:2], out[0][:2]) < MIN_LEG_M:
        out.pop(0)
    return out


def pieces(start: Sequence[float], waypoints: Sequence[Sequence[float]], step: float) -> list[list[float]]:
    """The waypoints with points put in between so that no leg from start is longer than step."""
    out, here = [], np.asarray(start[:2], dtype=np.float64)
    for waypoint in waypoints:
        target = np.asarray(waypoint[:2], dtype=np.float64)
        count = max(1, math.ceil(float(np.linalg.norm(target - here)) / step - 1e-9))
        out += [[float(v) for v in here + (target - here) * k / count] for k in range(1, count + 1)]
        here = target
    return out


def clip_length(points: np.ndarray, max_length: float) -> np.ndarray:
    """The polyline cut at max_length from its start."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = [points[0]] if len(points) else []
    left = max_length
    for a, b in zip(points[:-1], points[1:], strict=True):
        step = float(np.linalg.norm(b - a))
        if step >= left:
            out.append(a + (b - a) * (left / step) if step > 0 else b)
            break
        out.append(b)
        left -= step
    return np.array(out).reshape(-1, 2)


def _pose_list(pose: RoverPose) -> list[float]:
    return [pose.x, pose.y, pose.z, pose.heading, pose.roll, pose.pitch]
