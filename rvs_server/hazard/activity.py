"""Dynamic hazard detection as a background activity: one look along the rover's path per frame.

Per frame: borrow the PTU and the sensor from the device layer (a job that holds either makes the
frame `unknown`), point the sensor along the moving direction if it is not (pan 0, the configured
tilt), take one frame and the pose estimate of that instant; then, with the devices given back,
turn the frame into world points (the maps' artifact filter), build the low-resolution height map
of the corridor the footprint will sweep and its hazards (toolbox/mapping/corridor.py: the maps' own
DEM and hazard chain and mapping.toml thresholds), fold it into the rolling hazard memory the guard
reads, and publish the nearest hazard in the path with the frame's latency (from the frame in hand
to the event, wall clock).
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from rvs_server.activities import Activity
from rvs_server.devices.frame_points import SENSOR_DEVICE, FramePoints, FrameSettings
from toolbox.geometry import RoverPose
from toolbox.mapping import dem as dem_tools
from toolbox.mapping.corridor import CorridorParams, CorridorView, HazardMemory, Hit, Swept, corridor_view
from toolbox.mapping.hazard import HazardConfig

from .guard import HazardGuard, Seen, causes
from .record import FrameLog, FrameRecord, write_product

if TYPE_CHECKING:
    from rvs_server.host import Host

    from .settings import HazardSettings


class HazardActivity(Activity["Host"]):
    kind = "hazard"

    def __init__(self, server: Host, settings: HazardSettings, sensor: str, rate_hz: float,
                 stop_distance: float, product: Any):
        super().__init__(server, rate_hz)
        self.settings, self.sensor, self.stop_distance, self.product = settings, sensor, stop_distance, product
        self.device = SENSOR_DEVICE[sensor]
        mapping = server.settings_of("mapping")
        calibration = server.calibration()
        self.params = CorridorParams(
            body_length=calibration.rover_length_m, body_width=calibration.rover_width_m,
            side_margin=settings.side_margin_m, reach=settings.reach_m, cell=mapping.cell,
            max_reach_cells=settings.max_reach_cells,
            hazard=HazardConfig(slope_limit_deg=mapping.slope_limit_deg, step_limit=mapping.step_limit,
                                roughness_limit=mapping.roughness_limit,
                                step_min_cells=mapping.tof_step_min_cells if sensor == "tof"
                                else settings.stereo_step_min_cells))
        self.tilt_deg = settings.tof_tilt_deg if sensor == "tof" else settings.stereo_tilt_deg
        self.memory = HazardMemory(self.params)
        self._memory_lock = threading.Lock()
        self.newest: Seen | None = None
        self.last_unknown = ""
        self.log = FrameLog(product)           # frames.csv and stops.csv, written as they come
        self.views: list[CorridorView] = []    # the last frames', for the picture
        self.guard = HazardGuard(self)
        self.frames_of = FramePoints(server, FrameSettings(
            sensor, mapping.max_range_m if sensor == "tof" else settings.stereo_max_range_m,
            settings.stereo_resolution, settings.stereo_disparities,
            stereo_min_disparity=settings.stereo_min_disparity))

    # -- what the guard asks -----------------------------------------------------------------------
    def nearest(self, pose: tuple[float, float, float], direction: int, max_distance: float) -> Hit | None:
        with self._memory_lock:
            return self.memory.nearest(pose, direction, max_distance)

    def swept(self, pose: tuple[float, float, float], turn: float, distance: float) -> Swept:
        with self._memory_lock:
            return self.memory.swept(pose, turn, distance)

    def blind_reason(self, since_s: float, pose: RoverPose) -> str:
        """Why no frame counts as fresh for a drive begun at since_s, standing at pose."""
        newest, last = self.newest, self.log.last
        if last is not None and last.state == "unknown":
            return f"frame {last.seq} was unknown: {last.reason}"
        if newest is None:
            return "no frame was processed yet"
        if newest.sim_s < since_s:
            return f"the newest frame was taken {since_s - newest.sim_s:.1f} s before this move began"
        return f"the newest frame lies {math.dist((newest.pose.x, newest.pose.y), (pose.x, pose.y)):.2f} m back"

    def start(self) -> None:
        self.server.devices.rover.guard = self.guard
        super().start()

    # -- one frame ---------------------------------------------------------------------------------
    def frame(self, seq: int) -> dict[str, Any]:
        devices = self.server.devices
        with devices.sharing.borrow("ptu", self.device) as busy:
            if busy is not None:
                return self.unknown(seq, f"a job holds the {busy}")
            pan, tilt = self._point(devices)
            # The attitude of this instant: a frame seen with a drive-old roll or pitch tilts the
            # ground by the difference (campaign: 11 degree ground read as a 20 degree slope).
            roll, pitch = devices.rover.inclination()
            pose = replace(devices.rover.pose_estimate, roll=roll, pitch=pitch)
            truth = devices.rover.true_pose()
            sim_s = self.server.clock.now()
            frame = self.frames_of.grab(devices)
            taken = time.perf_counter()
        # The devices are given back before any processing: a job waits for the grab, never for this.
        points_camera, valid, camera_pose = self.frames_of.points(frame, pose, pan, tilt)
        points = dem_tools.view_points(points_camera, valid, camera_pose)
        view = corridor_view(points, (pose.x, pose.y, pose.heading), self.params, 1)
        direction = self.guard.direction
        with self._memory_lock:
            self.memory.update(view)
            hit = self.memory.nearest((pose.x, pose.y, pose.heading), direction, self.params.reach)
        self.newest = Seen(sim_s, pose)
        latency_ms = (time.perf_counter() - taken) * 1000.0
        self.views = (self.views + [view])[-self.settings.picture_frames:]
        record = FrameRecord(seq, sim_s, "hazard" if hit else "clear", hit, latency_ms, view.seen, len(points),
                             pose, pan, tilt, direction, truth=truth)
        self.log.frame(record)
        return record.event()

    def unknown(self, seq: int, reason: str) -> dict[str, Any]:
        self.last_unknown = reason
        record = FrameRecord(seq, self.server.clock.now(), "unknown", None, 0.0, 0.0, 0,
                             self.server.devices.rover.pose_estimate, math.nan, math.nan, self.guard.direction,
                             reason=reason)
        self.log.frame(record)
        return record.event()

    def _point(self, devices: Any) -> tuple[float, float]:
        """Pan 0 and the activity's tilt, moving there first if the unit stands elsewhere."""
        ptu = devices.ptu.ready_driver()
        position = devices.ptu.read_position()
        if abs(position[0]) > 0.5 or abs(position[1] - self.tilt_deg) > 0.5:
            ptu.move_to(0.0, self.tilt_deg, speed_deg_s=self.server.settings_of("ptu").default_speed_deg_s)
            ptu.wait_until_stopped(timeout_s=60.0)
            position = devices.ptu.read_position()
        return position

    # -- the end -------------------------------------------------------------------------------------
    def finish(self) -> dict[str, Any]:
        rover = self.server.devices.rover
        if rover.guard is self.guard:
            rover.guard = None
        write_product(self.product, self.log, self.views, self.memory, self.params, self.settings, self.sensor)
        p95 = self.log.latency_percentile(95)
        self.server.publish_threadsafe("product", {"name": self.product.name, "command": "hazard-start",
                                                   "path": str(self.product.path)})
        return {"activity": "hazard", "frames": self.frames, "rate": f"{self.measured_rate():.2f}",
                "hazards": self.log.states["hazard"], "stops": len(self.log.stops),
                "latency_ms": f"{p95:.1f}" if p95 is not None else "none",
                "product": self.product.name, "path": str(self.product.path)}

__all__ = ["HazardActivity", "causes"]
