"""The simulated test bed: one world, one rover on it, and the truth every emulated device shares.

The server builds one SimulatedTestbed when any device runs on the simulator. Emulated sensors ask
it where they are (the true camera pose, from the rover's pose and the PTU emulator's true angles
at that instant); products ask it for the truth of the moment (rover pose, PTU angles, true
heights and obstacles over a grid), which they store apart from what the sensors saw.

The world is built lazily, in a background thread started by `prebuild()`, because a 40 m scene
takes seconds and more than a gigabyte: a server that only drives the PTU never pays for it.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .clock import SimClock
from .config import WorldConfig
from .faults import InjectedFaults
from .motion import DriveError, Motion, PlannedMotion, execute, plan
from .rover import Rover, RoverConfig
from .world import World

WALK_STEP_M = 0.005   # a walking astronaut is moved once it is this far from where it stands
INCLINOMETER_NOISE_DEG = 0.1   # 1 sigma of roll and of pitch as the body's inclinometer reads them


@dataclass(frozen=True)
class Walk:
    """An astronaut walking along `points` (at least two) and back, over and over, at `speed` from
    simulation time `since`, standing still `pause` seconds at each end before it turns back."""

    points: tuple[tuple[float, float], ...]
    speed: float
    since: float
    pause: float = 0.0

    @property
    def start(self) -> tuple[float, float]:
        return self.points[0]

    @property
    def end(self) -> tuple[float, float]:
        return self.points[-1]

    def where(self, now: float) -> tuple[float, float, float]:
        """(x, y, heading) at simulation time `now`."""
        xy = np.asarray(self.points, dtype=float)
        legs = np.hypot(*np.diff(xy, axis=0).T)
        length = float(legs.sum())
        if length == 0 or self.speed <= 0:
            return (*self.points[0], 0.0)
        one_way = length / self.speed + self.pause
        t = max(0.0, now - self.since) % (2 * one_way)
        back = t >= one_way
        walked = min(length, self.speed * (t - one_way if back else t))
        distance = length - walked if back else walked
        leg = min(int(np.searchsorted(np.cumsum(legs), distance, side="right")), len(legs) - 1)
        along = distance - float(np.sum(legs[:leg]))
        (x0, y0), (x1, y1) = xy[leg], xy[leg + 1]
        share = along / legs[leg] if legs[leg] > 0 else 0.0
        heading = math.atan2(y1 - y0, x1 - x0) + (math.pi if back else 0.0)
        return float(x0 + share * (x1 - x0)), float(y0 + share * (y1 - y0)), math.atan2(math.sin(heading),
                                                                                    math.cos(heading))

    def record(self) -> dict:
        return {"from": list(self.start), "to": list(self.end), "via": [list(p) for p in self.points[1:-1]],
                "speed_m_s": self.speed, "pause_s": self.pause}


class SimulatedTestbed:
    def __init__(self, clock: SimClock, world_config: WorldConfig | None = None,
                 world_file: Path | None = None, rover_config: RoverConfig | None = None,
                 start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0), drive_error: DriveError | None = None):
        self.clock = clock
        self.world_config = world_config or WorldConfig()
        self.world_file = world_file
        self.rover_config = rover_config or RoverConfig()
        self.start_pose = start_pose
        self.drive_error = drive_error or DriveError()
        self._motion_rng = np.random.default_rng([self.world_config.seed, 17])
        self._inclinometer_rng = np.random.default_rng([self.world_config.seed, 23])  # readings between moves
        self._sun_sensor_rng = np.random.default_rng([self.world_config.seed, 29])
        self._sun_bias = np.radians(np.random.default_rng([self.world_config.seed, 31]).normal(
            0.0, self.world_config.sun_sensor.bias_deg, 2))
        self.odometer_m = 0.0
        self.contacts = 0
        self._world: World | None = None
        self._rover: Rover | None = None
        self._lock = threading.Lock()
        self._builder: threading.Thread | None = None
        self._build_error: BaseException | None = None
        # Set by the PTU device: the unit's true (pan, tilt) in degrees at a clock time (default now).
        self.ptu_angles: Callable[..., tuple[float, float]] = lambda at_s=None: (0.0, 0.0)
        # Broken hardware switched on by `sim-fault`; every emulator made on this bed asks its switch.
        self.faults = InjectedFaults()
        # The one astronaut `astronaut` puts in the world: its obstacle id, and its walk if it walks.
        self.astronaut_id: int | None = None
        self.walk: Walk | None = None
        self._obstacles_lock = threading.Lock()
        # The rover body and PTU angles of the latest trigger pulse: (pulse time, (body, pan, tilt)).
        self._rig_lock = threading.Lock()
        self._rig_pulse: tuple[float, tuple[np.ndarray, float, float]] | None = None

    # -- the world, built once ------------------------------------------------------------------

    def prebuild(self) -> None:
        """Start building the world in the background, so the first acquisition does not wait."""
        with self._lock:
            if self._world is None and self._builder is None:
                self._builder = threading.Thread(target=self._build_quietly, name="rvs-world-build", daemon=True)
                self._builder.start()

    def _build_quietly(self) -> None:
        try:
            _ = self.world
        except BaseException as exc:  # reported to whoever needs the world next
            self._build_error = exc

    def wait_for_build(self) -> None:
        """Wait for a background build to finish. While it runs, Open3D's scene building holds the
        interpreter for seconds at a time, long enough for serial-line timeouts to expire in other
        threads: jobs that drive the emulated devices start after it."""
        builder = self._builder
        if builder is not None and builder.is_alive():
            builder.join()

    def close(self) -> None:
        """Wait for a world still being built: Open3D's threads must not outlive the interpreter."""
        builder = self._builder
        if builder is not None:
            builder.join()

    @property
    def world(self) -> World:
        with self._lock:
            if self._world is None:
                if self._build_error is not None:
                    raise self._build_error
                world = World.load(self.world_file) if self.world_file else World.build(self.world_config)
                self._rover = Rover(world, self.rover_config, *self.start_pose)
                self._world = world
            return self._world

    @property
    def ready(self) -> bool:
        return self._world is not None

    def extent(self) -> tuple[float, float, float, float] | None:
        """(x_min, x_max, y_min, y_max) of the ground the rover can drive on: the world's bounds once
        built; before that the configured size (the built world spans at least that), or None for a
        world file not loaded yet."""
        if self._world is not None:
            return self._world.bounds
        if self.world_file is None:
            half_x, half_y = (size / 2 for size in self.world_config.size_m)
            return (-half_x, half_x, -half_y, half_y)
        return None

    @property
    def rover(self) -> Rover:
        _ = self.world
        assert self._rover is not None
        return self._rover

    # -- poses and truth ------------------------------------------------------------------------

    def sensor_pose(self, sensor: str, at_s: float | None = None) -> np.ndarray:
        """The true camera-to-world pose of a sensor now (OpenCV camera frame), a walking astronaut
        brought to where it is at `at_s` (a trigger pulse's time; default now) for the sensor to see.

        Every sensor asked for the same pulse gets the rover body and PTU angles of the first ask:
        the stereo pair's two cameras take one pulse in turn, and a drive stepping the rover
        between them (5 cm a step, milliseconds apart at a simulation speed-up) put the right camera
        5 cm off the left, a pair no matcher can make ground of (the stereo guard's false stops)."""
        self.update_obstacles(at_s)
        with self._rig_lock:
            if at_s is None or self._rig_pulse is None or self._rig_pulse[0] != at_s:
                rig = (self.rover.body_to_world, *self.ptu_angles())
                if at_s is not None:
                    self._rig_pulse = (at_s, rig)
            else:
                rig = self._rig_pulse[1]
        body, pan, tilt = rig
        return self.rover.sensor_to_world(sensor, pan, tilt, body=body)

    def drive(self, turn_rad: float, distance_m: float, step_height: float = 0.10) -> Motion:
        """Execute one motion command with the rover's drive error (drivers/sim/motion.py); the
        rover stays where it really ended up, and contacts with true obstacles are counted."""
        start = self.rover.pose
        try:
            motion = execute(self.rover, turn_rad, distance_m, self.drive_error, self._motion_rng, step_height)
        except ValueError:  # off the world's edge: the rover stays where it was
            self.rover.place(*start)
            raise
        self.odometer_m += abs(motion.distance_m)
        self.contacts += motion.contacts
        return motion

    def plan_drive(self, turn_rad: float, distance_m: float) -> PlannedMotion:
        """The true trajectory of one motion command, with the rover's drive error; the rover does
        not move until step_rover takes it along (a drive that can stop part-way)."""
        return plan(self.rover.pose, turn_rad, distance_m, self.drive_error, self._motion_rng)

    def leaves_world(self, poses: np.ndarray) -> str | None:
        """Where a trajectory's footprint would leave the terrain (a sentence), or None."""
        x_min, x_max, y_min, y_max = self.world.bounds
        c = self.rover.config
        reach = math.hypot(c.body_length_m, c.body_width_m) / 2
        outside = ((poses[:, 0] - reach < x_min) | (poses[:, 0] + reach > x_max)
                   | (poses[:, 1] - reach < y_min) | (poses[:, 1] + reach > y_max))
        if not outside.any():
            return None
        x, y = poses[int(np.argmax(outside)), :2]
        return (f"its footprint at ({x:.2f}, {y:.2f}) leaves the terrain [{x_min:g}, {x_max:g}] x "
                f"[{y_min:g}, {y_max:g}] m")

    def step_rover(self, pose: tuple[float, float, float], step_height: float = 0.10) -> bool:
        """Move the rover to the next sample of a planned motion; True if its footprint now covers a
        true obstacle (counted). Off the world's edge: ValueError, the rover stays where it was."""
        rover = self.rover
        before = rover.pose
        try:
            rover.place(*pose)
        except ValueError:
            rover.place(*before)
            raise
        self.odometer_m += float(np.hypot(pose[0] - before[0], pose[1] - before[1]))
        contact = rover.collides(step_height)
        self.contacts += int(contact)
        return contact

    def inclinometer(self, noise_deg: float = INCLINOMETER_NOISE_DEG) -> tuple[float, float]:
        """Roll and pitch (radians) read now, as inclination() but from their own noise stream, so
        readings taken beside a drive (a hazard frame) never change the drive's errors."""
        roll, pitch = self.rover.roll_pitch()
        noise = np.radians(self._inclinometer_rng.normal(0.0, noise_deg, 2))
        return roll + float(noise[0]), pitch + float(noise[1])

    def inclination(self, noise_deg: float = INCLINOMETER_NOISE_DEG) -> tuple[float, float]:
        """Roll and pitch (radians) as an inclinometer on the body reads them: truth plus noise."""
        roll, pitch = self.rover.roll_pitch()
        noise = np.radians(self._motion_rng.normal(0.0, noise_deg, 2))
        return roll + float(noise[0]), pitch + float(noise[1])

    def sun_sensor(self) -> np.ndarray | None:
        """The unit vector toward the sun in the rover's body frame as its sun sensor reads it now
        (world.toml [sun_sensor]: truth turned by the sensor's fixed alignment bias and a reading's
        white noise), or None when the sun stands outside the sensor's field of view."""
        config = self.world_config.sun_sensor
        body = self.rover.body_to_world[:3, :3].T @ np.asarray(self.world.sun.direction(), dtype=np.float64)
        if math.degrees(math.acos(float(np.clip(body[2], -1.0, 1.0)))) > config.half_fov_deg:
            return None
        # Error angles about two axes across the sun direction, each N(0, sigma) per axis.
        across = np.cross(body, [1.0, 0.0, 0.0] if abs(body[0]) < 0.9 else [0.0, 1.0, 0.0])
        across /= np.linalg.norm(across)
        other = np.cross(body, across)
        tilt = self._sun_bias + np.radians(self._sun_sensor_rng.normal(0.0, config.noise_deg, 2))
        reading = body + tilt[0] * across + tilt[1] * other
        return reading / np.linalg.norm(reading)

    def truth(self) -> dict:
        """The state of the moment, for a product's truth/ folder."""
        self.update_obstacles()
        rover = self.rover
        pan, tilt = self.ptu_angles()
        roll, pitch = rover.roll_pitch()
        return {
            "time_s": self.clock.now(),
            "rover": {"x": rover.x, "y": rover.y, "heading_rad": rover.heading, "roll_rad": roll,
                      "pitch_rad": pitch, "body_to_world": rover.body_to_world.tolist(),
                      "odometer_m": self.odometer_m, "contacts": self.contacts},
            "ptu": {"pan_deg": pan, "tilt_deg": tilt},
            "sensors": {name: rover.sensor_to_world(name, pan, tilt).tolist() for name in rover.sensors},
            "world": {"seed": self.world_config.seed, "file": str(self.world_file) if self.world_file else None,
                      "sun": self.world.sun.model_dump() if hasattr(self.world.sun, "model_dump") else None},
            "obstacles": self.obstacles(),
        }

    # -- obstacles no map knew ------------------------------------------------------------------

    def obstacles(self) -> list[dict]:
        """The obstacles added to the world (World.obstacles), a walking astronaut's walk with it."""
        records = self.world.obstacles()
        walk = self.walk
        for record in records:
            if walk is not None and record["id"] == self.astronaut_id:
                record["walk"] = walk.record()
        return records

    def drop_rock(self, x: float, y: float, height: float, diameter: float, seed: int | None = None) -> dict:
        """Drop a rock (World.add_rock) anywhere but on the rover's true footprint; its record."""
        rock = self.world.add_rock(x, y, height, diameter, seed, keep_clear=self.rover.footprint())
        return self._record(rock)

    def remove_obstacle(self, obstacle_id: int) -> None:
        with self._obstacles_lock:
            self.world.remove_obstacle(obstacle_id)
            if obstacle_id == self.astronaut_id:
                self.astronaut_id, self.walk = None, None

    def clear_rocks(self) -> list[int]:
        """Take every dropped rock away (the astronaut stays); their ids."""
        return self.world.clear_obstacles("rock")

    def place_astronaut(self, x: float, y: float, to: tuple[float, float] | None = None,
                        speed: float = 0.5, then: tuple[float, float] | None = None, pause: float = 0.0) -> dict:
        """Stand the one astronaut at (x, y) (moving it if it is there), or, with `to`, start it walking
        from (x, y) to `to` (and on to `then`, turning there) and back at `speed` (m/s of simulation
        time), standing `pause` seconds at each end. A standing astronaut may not be put on the rover;
        a walking one walks where it walks (every corner of its walk must lie in the world)."""
        with self._obstacles_lock:
            world = self.world
            clear = self.rover.footprint() if to is None else None
            heading = 0.0 if to is None else math.atan2(to[1] - y, to[0] - x)
            if self.astronaut_id is None:
                self.astronaut_id = world.add_astronaut(x, y, heading, keep_clear=clear)
                placed = True
            else:
                placed = False
            try:
                for corner in (to, then):
                    if corner is not None:                              # refused if a corner is off the world
                        world.move_obstacle(self.astronaut_id, *corner, heading)
                world.move_obstacle(self.astronaut_id, x, y, heading, keep_clear=clear)
            except ValueError:
                if placed:
                    world.remove_obstacle(self.astronaut_id)
                    self.astronaut_id = None
                elif self.walk is not None:
                    self._step(self.walk)
                raise
            corners = ((x, y),) + tuple(tuple(c) for c in (to, then) if c is not None)
            self.walk = None if to is None else Walk(corners, speed, self.clock.now(), pause)
            return self._record(self.astronaut_id)

    def update_obstacles(self, at_s: float | None = None) -> None:
        """Bring a walking astronaut to where it is at clock time `at_s` (default now): sensors ask
        for their pose before each render (the stereo pair with its pulse's time, so the second
        camera sees the walker where the first did); truth() before each record."""
        walk = self.walk
        if walk is None or not self.ready:
            return
        with self._obstacles_lock:
            if self.walk is walk:
                self._step(walk, at_s)

    def _step(self, walk: Walk, at_s: float | None = None) -> None:
        x, y, heading = walk.where(self.clock.now() if at_s is None else at_s)
        record = self._record(self.astronaut_id)
        if math.hypot(x - record["x"], y - record["y"]) >= WALK_STEP_M or heading != record["heading_rad"]:
            self.world.move_obstacle(self.astronaut_id, x, y, heading)

    def person_truth(self, sensor: str, half_fov_deg: tuple[float, float], max_range_m: float,
                     at_s: float | None = None) -> dict | None:
        """Where the astronaut truly stands at clock time `at_s` (default now; a frame's truth is
        where the person was in the middle of its exposure): x, y, its ground z, heading, and how much of it the
        sensor sees: the share of points along its body axis (0.1 to 1.7 of its height) inside the
        sensor's field of view and range whose ray meets the person before anything else (a rock
        between hides it). None without an astronaut."""
        with self._obstacles_lock:
            if self.walk is not None:
                self._step(self.walk)
            if self.astronaut_id is None:
                return None
            record = self._record(self.astronaut_id)
            if self.walk is not None and at_s is not None:
                record["x"], record["y"], record["heading_rad"] = self.walk.where(at_s)
        x, y, height = record["x"], record["y"], record["height_m"]
        ground = float(self.world.ground_height_at(x, y))
        camera = self.sensor_pose(sensor)
        axis = np.column_stack([np.full(17, x), np.full(17, y), ground + height * np.linspace(0.1, 0.9, 17)])
        origin = camera[:3, 3]
        towards = axis - origin
        distance = np.linalg.norm(towards, axis=1)
        in_camera = towards @ camera[:3, :3]          # camera axes: x right, y down, z forward
        tan_x, tan_y = np.tan(np.radians(half_fov_deg))
        in_view = ((in_camera[:, 2] > 0) & (np.abs(in_camera[:, 0]) <= tan_x * in_camera[:, 2])
                   & (np.abs(in_camera[:, 1]) <= tan_y * in_camera[:, 2]) & (distance <= max_range_m))
        rays = np.column_stack([np.repeat(origin[None], len(axis), axis=0), towards / distance[:, None]])
        hit, _ = self.world.surface.cast(rays.astype(np.float32))
        reach = math.hypot(record.get("width_m", 0.5), record.get("depth_m", 0.3)) / 2 + 0.05
        unblocked = hit >= distance - reach             # the first hit is the person's own near side
        pan, tilt = self.ptu_angles(at_s)
        return {"id": record["id"], "x": x, "y": y, "z": ground, "heading_rad": record["heading_rad"],
                "height_m": height, "visible": float(np.mean(in_view & unblocked)),
                "range_m": float(math.hypot(x - origin[0], y - origin[1])), "pan_deg": pan, "tilt_deg": tilt}

    def _record(self, obstacle_id: int) -> dict:
        return next(o for o in self.world.obstacles() if o["id"] == obstacle_id)
