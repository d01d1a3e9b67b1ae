"""The simulated hopping rover: a spring-launched body with one camera, hopping over a World.

After the hopping paper's simulation: the rover turns to the commanded heading, the spring launches
it (with seeded errors in speed, elevation and heading, and optionally a spin), it flies a parabola
under gravity alone while its camera, looking 45 degrees down along the direction of travel, records
frames at a fixed rate, touches the terrain (the ground, or a rock's side), bounces a few times in
directions it cannot know, and comes to rest. `Hopper.hop` returns a HopRecord with the frames, their
true poses, the truth of every phase, and what the rover's accelerometer and sun sensor read.

    world = World.build(WorldConfig(...))
    hopper = Hopper(world, HopperConfig(), x=0.0, y=0.0)
    record = hopper.hop(speed=1.37, elevation_deg=60.0, heading_deg=90.0)
    record.save("data/hop-001")

Files: hopper_config.py (the settings), hopper_flight.py (the physics: arc, touchdown, bounces,
rest), hopper_record.py (the record, its truth and save/load). Frames: world x east, y north, z up;
body x forward, y left, z up, origin at the centre of mass; camera as OpenCV. Radians inside,
degrees in the config and in the arguments of `hop`.
"""
from __future__ import annotations

import math

import numpy as np

from drivers.avt import CameraSettings
from drivers.avt_sensor import auto_exposure_us, sensor_image

from . import hopper_flight as flight
from .hopper_config import HopperConfig
from .hopper_record import HopRecord
from .render import render
from .world import World

__all__ = ["Hopper", "HopperConfig", "HopRecord"]

DOWN = np.array([0.0, 0.0, -1.0])
STREAMS = ("launch", "bounce", "sensor", "attitude")   # independent random streams of one hop


class Hopper:
    """A hopping rover resting on a world at ground position (x, y), facing `heading` (radians, CCW from east)."""

    def __init__(self, world: World, config: HopperConfig | None = None, x: float = 0.0, y: float = 0.0,
                 heading: float = 0.0):
        self.world = world
        self.config = config or HopperConfig()
        self.camera = self.config.camera.intrinsics()
        self.camera_to_body = self.config.camera.to_body()
        self._samples = flight.body_samples(self.config.body_radius_m)
        self.hops = 0
        self.place(x, y, heading)

    # ------------------------------------------------------------------------------ state
    def place(self, x: float, y: float, heading: float) -> None:
        """Put the hopper at rest on the ground at (x, y), facing heading (radians)."""
        self.x, self.y, self.heading = float(x), float(y), _wrap(float(heading))
        self.body_to_world = np.eye(4)
        self.body_to_world[:3, :3] = flight.resting_attitude(self.world, self.x, self.y, self.heading,
                                                             self.config.body_radius_m)
        self.body_to_world[:3, 3] = flight.resting_centre(self.world, self.x, self.y, self._samples)

    @property
    def ground_position(self) -> np.ndarray:
        """(3,) the ground point under the centre of mass."""
        return np.array([self.x, self.y, float(self.world.height_at(self.x, self.y))])

    def camera_to_world(self) -> np.ndarray:
        """4x4 true camera pose at rest."""
        return self.body_to_world @ self.camera_to_body

    # ------------------------------------------------------------------------------ the hop
    def hop(self, speed: float, elevation_deg: float, heading_deg: float,
            seed: int | np.random.Generator | None = None, render_frames: bool = True) -> HopRecord:
        """Hop with the commanded launch speed (m/s), elevation and heading (degrees, heading CCW from east).

        seed: an int, a Generator, or None for the config's seed mixed with the hop count (so a
        sequence of hops is repeatable). render_frames=False skips the images (fast physics only).
        Raises ValueError on a bad command and flight.OffTerrain if the hop leaves the world; the
        hopper then stays where it was.
        """
        _check_command(speed, elevation_deg)
        seed_used, streams = self._streams(seed)
        c, g = self.config, self.config.gravity_mps2
        elevation, heading = math.radians(elevation_deg), math.radians(heading_deg)
        # Turn in place to face the hop (the camera looks along the direction of travel).
        start = (self.x, self.y, self.heading)
        self.place(self.x, self.y, heading)
        launch_pose, launch_ground, launch_yaw = self.body_to_world.copy(), self.ground_position, self.heading
        try:
            # The launch actually flown: the command with the spring's errors.
            velocity, spin = self._launch(speed, elevation, heading, streams["launch"])
            # The parabola until the body first touches the terrain.
            landing = flight.first_contact(self.world, launch_pose[:3, 3], velocity, g, self._samples,
                                           c.contact_step_s)
            # Secondary bounces, unseen by the rover, then rest where the last one ends.
            bounces, turn = self._bounces(landing, streams["bounce"])
            final = bounces[-1] if bounces else landing
            self.place(final.centre[0], final.centre[1], heading + turn)
        except flight.OffTerrain:
            self.place(*start)
            raise
        # The camera during the flight, one pose per frame.
        times = frame_times(landing.time, c.camera.frame_rate_hz)
        poses = flight.flight_body_poses(launch_pose, velocity, spin, times, g) @ self.camera_to_body
        before_pose, after_pose = launch_pose @ self.camera_to_body, self.camera_to_world()
        images = self._images(launch_pose, velocity, spin, times, landing.time, before_pose, after_pose,
                              streams["sensor"]) if render_frames else _no_images(self.camera)
        self.hops += 1
        return HopRecord(
            config=c, camera=self.camera, camera_to_body=self.camera_to_body.copy(), seed=seed_used,
            **images, timestamps=times, camera_to_world=poses, before_pose=before_pose, after_pose=after_pose,
            commanded_speed=float(speed), commanded_elevation=elevation, commanded_heading=heading,
            launch_centre=launch_pose[:3, 3].copy(), launch_ground=launch_ground, launch_yaw=launch_yaw,
            launch_velocity=velocity, spin=spin, flight_time=landing.time, landing_centre=landing.centre,
            landing_velocity=landing.velocity, contact_point=landing.point,
            contact_rock=self._rock_at(landing.point),
            bounce_centres=np.array([b.centre for b in bounces]).reshape(-1, 3),
            settled_centre=self.body_to_world[:3, 3].copy(), settled_ground=self.ground_position,
            settled_yaw=self.heading, **self._attitude_sensors(before_pose, after_pose, streams["attitude"]))

    # ------------------------------------------------------------------------------ steps
    def _streams(self, seed) -> tuple[int | None, dict[str, np.random.Generator]]:
        """Independent streams per part, so turning off one error never changes the others."""
        if isinstance(seed, np.random.Generator):
            return None, dict(zip(STREAMS, seed.spawn(len(STREAMS)), strict=True))
        if seed is None:
            seed = int(np.random.SeedSequence([self.config.seed, self.hops]).generate_state(1)[0])
        children = np.random.SeedSequence(int(seed)).spawn(len(STREAMS))
        return int(seed), {name: np.random.default_rng(child) for name, child in zip(STREAMS, children, strict=True)}

    def _launch(self, speed: float, elevation: float, heading: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Launch velocity (world) and spin (body, rad/s) with the configured errors."""
        e = self.config.launch_errors
        speed = speed * (1.0 + rng.normal(0.0, e.speed_fraction))
        elevation = elevation + rng.normal(0.0, math.radians(e.elevation_deg))
        heading = heading + rng.normal(0.0, math.radians(e.heading_deg))
        spin = rng.normal(0.0, math.radians(e.spin_deg_s), 3)
        return flight.launch_velocity(speed, elevation, heading), spin

    def _bounces(self, landing: flight.Contact, rng: np.random.Generator) -> tuple[list[flight.Contact], float]:
        """The bounces after the first touchdown, and how far they turned the body (radians)."""
        b = self.config.bounce
        contacts = flight.bounce_contacts(self.world, landing, self.config.gravity_mps2, self._samples,
                                          self.config.contact_step_s, b.count, b.restitution,
                                          math.radians(b.spread_deg),
                                          tuple(math.radians(v) for v in b.elevation_range_deg), rng)
        return contacts, float(rng.normal(0.0, math.radians(b.yaw_deg), len(contacts)).sum())

    def _rock_at(self, point: np.ndarray) -> int:
        return int(self.world.rock_at(point[0], point[1]))

    def _images(self, launch_pose, velocity, spin, times, flight_time, before_pose, after_pose,
                rng: np.random.Generator) -> dict:
        """The before, flight and after images. Exposure is set on the ground before launch and kept."""
        cam = self.config.camera
        before_radiance = self._radiance([before_pose])
        settings = CameraSettings(auto_exposure=True, target_grey_level=cam.target_grey_level, gain_db=cam.gain_db)
        exposure_us = min(auto_exposure_us(before_radiance, settings), cam.max_exposure_ms * 1e3)
        blur = blur_offsets(exposure_us * 1e-6, cam.blur_samples if cam.motion_blur else 1)
        frames = np.empty((len(times), self.camera.height, self.camera.width), dtype=np.uint8)
        for i, t in enumerate(times):
            sub_times = np.clip(t + blur, 0.0, flight_time)
            body_poses = flight.flight_body_poses(launch_pose, velocity, spin, sub_times, self.config.gravity_mps2)
            frames[i] = self._develop(self._radiance(body_poses @ self.camera_to_body), exposure_us, rng)
        return {"exposure_s": exposure_us * 1e-6, "frames": frames,
                "before": self._develop(before_radiance, exposure_us, rng),
                "after": self._develop(self._radiance([after_pose]), exposure_us, rng)}

    def _radiance(self, camera_poses) -> np.ndarray:
        """Mean rendered radiance over the poses (one pose: a still frame; several: motion blur)."""
        total = np.zeros((self.camera.height, self.camera.width), dtype=np.float32)
        for pose in camera_poses:
            total += render(self.world, pose, self.camera).intensity
        return total / np.float32(len(camera_poses))

    def _develop(self, radiance: np.ndarray, exposure_us: float, rng: np.random.Generator) -> np.ndarray:
        return sensor_image(radiance, exposure_us, self.config.camera.gain_db, rng)

    def _attitude_sensors(self, before_pose: np.ndarray, after_pose: np.ndarray, rng: np.random.Generator) -> dict:
        """Gravity in the camera frame (true and as the accelerometer reads it) and the sun sensor's
        body heading, at rest before launch and after settling."""
        s = self.config.sensors
        truth = {"true_gravity_launch": before_pose[:3, :3].T @ DOWN,
                 "true_gravity_settled": after_pose[:3, :3].T @ DOWN}
        gravity_sigma, sun_sigma = math.radians(s.gravity_deg), math.radians(s.sun_heading_deg)
        return {**truth,
                "imu_gravity_launch": noisy_direction(truth["true_gravity_launch"], gravity_sigma, rng),
                "imu_gravity_settled": noisy_direction(truth["true_gravity_settled"], gravity_sigma, rng),
                "sun_heading_launch": _wrap(self._yaw(before_pose) + rng.normal(0.0, sun_sigma)),
                "sun_heading_settled": _wrap(self._yaw(after_pose) + rng.normal(0.0, sun_sigma))}

    def _yaw(self, camera_to_world: np.ndarray) -> float:
        """Heading of the body's x axis from a camera pose."""
        body = camera_to_world @ np.linalg.inv(self.camera_to_body)
        return math.atan2(body[1, 0], body[0, 0])


# ---------------------------------------------------------------------------------- helpers
def frame_times(flight_time: float, frame_rate: float) -> np.ndarray:
    """Frame timestamps from launch (t = 0) to the first touchdown, one every 1 / frame_rate."""
    return np.arange(int(math.floor(flight_time * frame_rate + 1e-9)) + 1) / frame_rate


def blur_offsets(exposure: float, samples: int) -> np.ndarray:
    """Sub-frame times relative to a frame's timestamp: `samples` evenly spread over an exposure
    centred on it (one sample: the timestamp itself, no blur)."""
    return exposure * ((np.arange(samples) + 0.5) / samples - 0.5)


def noisy_direction(direction: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Unit direction tilted by a random angle of `sigma` (radians) per perpendicular axis."""
    noise = rng.normal(0.0, sigma, 3)
    noise -= direction * (noise @ direction)
    tilted = direction + noise
    return tilted / np.linalg.norm(tilted)


def _no_images(camera) -> dict:
    return {"exposure_s": None, "frames": np.zeros((0, camera.height, camera.width), np.uint8),
            "before": np.zeros((0, 0), np.uint8), "after": np.zeros((0, 0), np.uint8)}


def _check_command(speed: float, elevation_deg: float) -> None:
    if not (math.isfinite(speed) and speed > 0):
        raise ValueError(f"hop speed must be a positive number of m/s, got {speed!r}")
    if not 0.0 < elevation_deg < 90.0:
        raise ValueError(f"hop elevation must lie between 0 and 90 degrees (exclusive), got {elevation_deg!r}")


def _wrap(angle: float) -> float:
    """Angle in (-pi, pi]."""
    return float(math.atan2(math.sin(angle), math.cos(angle)))
