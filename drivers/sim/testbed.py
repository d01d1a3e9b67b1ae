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
from pathlib import Path
from typing import Callable

import numpy as np

from .clock import SimClock
from .config import WorldConfig
from .faults import InjectedFaults
from .motion import DriveError, Motion, PlannedMotion, execute, plan
from .rover import Rover, RoverConfig
from .world import World


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
        self.odometer_m = 0.0
        self.contacts = 0
        self._world: World | None = None
        self._rover: Rover | None = None
        self._lock = threading.Lock()
        self._builder: threading.Thread | None = None
        self._build_error: BaseException | None = None
        # Set by the PTU device: the unit's true (pan, tilt) in degrees right now.
        self.ptu_angles: Callable[[], tuple[float, float]] = lambda: (0.0, 0.0)
        # Broken hardware switched on by `sim-fault`; every emulator made on this bed asks its switch.
        self.faults = InjectedFaults()

    # -- the world, built once ------------------------------------------------------------------

    def prebuild(self) -> None:
        """Start building the world in the background, so the first acquisition does not wait."""
        with self._lock:
            if self._world is None and self._builder is None:
                self._builder = threading.Thread(target=self._build_quietly, name="rvs-world-build", daemon=True)
                self._builder.start()

    def _build_quietly(self) -> None:
        try:
            self.world
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
        self.world
        assert self._rover is not None
        return self._rover

    # -- poses and truth ------------------------------------------------------------------------

    def sensor_pose(self, sensor: str) -> np.ndarray:
        """The true camera-to-world pose of a sensor now (OpenCV camera frame)."""
        pan, tilt = self.ptu_angles()
        return self.rover.sensor_to_world(sensor, pan, tilt)

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

    def inclination(self, noise_deg: float = 0.1) -> tuple[float, float]:
        """Roll and pitch (radians) as an inclinometer on the body reads them: truth plus noise."""
        roll, pitch = self.rover.roll_pitch()
        noise = np.radians(self._motion_rng.normal(0.0, noise_deg, 2))
        return roll + float(noise[0]), pitch + float(noise[1])

    def truth(self) -> dict:
        """The state of the moment, for a product's truth/ folder."""
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
        }
