"""The simulated rover: pose on the terrain, mast and pan-tilt unit, and where its sensors are.

Modelled on the thesis' test bed: a Pioneer 3-AT (about 0.5 m square, four wheels) carrying an
aluminium frame with a pan-tilt unit on top; on the PTU a stereo pair of cameras with the SR4000
time-of-flight camera between them. The thesis gives no mast height or baseline, so the defaults
put the cameras about 1.5 m above the ground, 0.25 m apart.

Frames (metres, radians inside, degrees at the boundary for PTU angles):
- world: x east, y north, z up.
- rover: x forward, y left, z up; origin on the ground midway between the four wheel contacts.
  Heading is the yaw of rover x, counter-clockwise from world x (east).
- head: the PTU's moving frame, origin where pan and tilt axes meet; equal to the rover axes at
  pan = tilt = 0. Positive pan turns the head to the right (clockwise seen from above), positive
  tilt raises the view (the thesis' convention).
- camera: OpenCV, x right, y down, z forward.

Each sensor has three mounts (sensor-to-head): `nominal` from the configuration (the drawing),
`true` = nominal with a seeded assembly error (where the sensor really is; rendering uses it), and
`calibrated` = true with a smaller seeded calibration error (what a calibration would report; RVS
gets these). The errors come from the rover's seed, so they are repeatable.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolbox.geometry import CAMERA_AXES_IN_HEAD, rotation_rpy, rotation_y, rotation_z

from .world import World


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorMount(_Model):
    """A sensor's pose on the PTU head: optical centre position and a small rotation away from
    looking straight along head x (roll about x, then pitch about y, then yaw about z, degrees)."""

    position_m: tuple[float, float, float]
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_head(self) -> np.ndarray:
        """4x4 sensor (camera frame) to head transform."""
        pose = np.eye(4)
        pose[:3, :3] = rotation_rpy(*np.radians(self.rotation_deg)) @ CAMERA_AXES_IN_HEAD
        pose[:3, 3] = self.position_m
        return pose


class MountError(_Model):
    """Standard deviations of a seeded mount error, per axis."""

    rotation_deg: float = Field(ge=0.0)
    translation_m: float = Field(ge=0.0)


def _default_mounts() -> dict[str, SensorMount]:
    return {"left": SensorMount(position_m=(0.05, 0.125, 0.08)),
            "right": SensorMount(position_m=(0.05, -0.125, 0.08)),
            "tof": SensorMount(position_m=(0.07, 0.0, 0.03))}


class RoverConfig(_Model):
    seed: int = 7
    body_length_m: float = Field(0.55, gt=0)      # footprint used for collision checks
    body_width_m: float = Field(0.50, gt=0)
    wheelbase_m: float = Field(0.38, gt=0)        # front to rear wheel contact
    track_m: float = Field(0.40, gt=0)            # left to right wheel contact
    wheel_radius_m: float = Field(0.11, gt=0)
    wheel_width_m: float = Field(0.09, gt=0)
    # Where pan and tilt axes meet, in the rover frame (on top of the mast).
    ptu_position_m: tuple[float, float, float] = (0.10, 0.0, 1.40)
    mounts: dict[str, SensorMount] = Field(default_factory=_default_mounts)
    assembly_error: MountError = MountError(rotation_deg=0.5, translation_m=0.003)
    calibration_error: MountError = MountError(rotation_deg=0.05, translation_m=0.0005)


class Rover:
    """A rover standing on a world: set its (x, y, heading); height and tilt follow the terrain."""

    def __init__(self, world: World, config: RoverConfig | None = None, x: float = 0.0, y: float = 0.0,
                 heading: float = 0.0):
        self.world = world
        self.config = config or RoverConfig()
        self.true_mounts, self.calibrated_mounts = _seeded_mounts(self.config)
        self.place(x, y, heading)

    # ------------------------------------------------------------------------------ pose
    def place(self, x: float, y: float, heading: float) -> None:
        """Put the rover at world (x, y) with heading (radians, CCW from east) and settle it."""
        self.x, self.y, self.heading = float(x), float(y), float(heading)
        self.wheel_contacts = self._wheel_contacts()
        self.body_to_world = _settled_pose(self.wheel_contacts)

    @property
    def pose(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.heading)

    def roll_pitch(self) -> tuple[float, float]:
        """Roll (left side up positive) and pitch (nose down positive) of the body, radians."""
        r = self.body_to_world[:3, :3]
        return math.atan2(r[2, 1], r[2, 2]), -math.asin(np.clip(r[2, 0], -1.0, 1.0))

    def _wheel_contacts(self) -> np.ndarray:
        """World xyz of the four wheel contacts (front-left, front-right, rear-left, rear-right).

        A wheel rests on the highest terrain under its contact patch, so a rock under a wheel
        lifts that corner.
        """
        c = self.config
        along = np.array([1, 1, -1, -1]) * c.wheelbase_m / 2
        across = np.array([1, -1, 1, -1]) * c.track_m / 2
        patch_along = np.linspace(-c.wheel_radius_m / 2, c.wheel_radius_m / 2, 5)
        patch_across = np.linspace(-c.wheel_width_m / 2, c.wheel_width_m / 2, 3)
        da, dc = np.meshgrid(patch_along, patch_across, indexing="ij")
        local_x = along[:, None] + da.ravel()[None, :]
        local_y = across[:, None] + dc.ravel()[None, :]
        cos_h, sin_h = math.cos(self.heading), math.sin(self.heading)
        wx = self.x + cos_h * local_x - sin_h * local_y
        wy = self.y + sin_h * local_x + cos_h * local_y
        z = np.max(self.world.height_at(wx, wy), axis=1)
        if np.isnan(z).any():
            raise ValueError(f"rover at ({self.x:.2f}, {self.y:.2f}) has a wheel off the terrain")
        centre_x = self.x + cos_h * along - sin_h * across
        centre_y = self.y + sin_h * along + cos_h * across
        return np.stack([centre_x, centre_y, z], axis=1)

    # ------------------------------------------------------------------------------ sensors
    @property
    def sensors(self) -> list[str]:
        return list(self.config.mounts)

    def head_to_world(self, pan_deg: float, tilt_deg: float, body: np.ndarray | None = None) -> np.ndarray:
        """4x4 PTU head frame to world for the given PTU angles (degrees), on the body pose `body`
        (4x4; default the rover's own now)."""
        body = self.body_to_world if body is None else body
        return body @ self._head_to_body(math.radians(pan_deg), math.radians(tilt_deg))

    def sensor_to_world(self, sensor: str, pan_deg: float = 0.0, tilt_deg: float = 0.0,
                        calibrated: bool = False, body: np.ndarray | None = None) -> np.ndarray:
        """4x4 camera-to-world pose of a sensor (OpenCV camera frame) for the given PTU angles.

        calibrated=False is the truth (what to render with); True uses the calibrated mount, i.e.
        what RVS computes from its calibration and the PTU angles. `body`: a body-to-world pose
        read earlier (default the rover's now).
        """
        mounts = self.calibrated_mounts if calibrated else self.true_mounts
        if sensor not in mounts:
            raise KeyError(f"no sensor {sensor!r}; the rover has {', '.join(mounts)}")
        return self.head_to_world(pan_deg, tilt_deg, body) @ mounts[sensor].to_head()

    def _head_to_body(self, pan: float, tilt: float) -> np.ndarray:
        pose = np.eye(4)
        pose[:3, :3] = rotation_z(-pan) @ rotation_y(-tilt)
        pose[:3, 3] = self.config.ptu_position_m
        return pose

    # ------------------------------------------------------------------------------ footprint
    def footprint(self) -> np.ndarray:
        """World (x, y) of the body's four corners, counter-clockwise from front-left."""
        half_l, half_w = self.config.body_length_m / 2, self.config.body_width_m / 2
        local = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])
        cos_h, sin_h = math.cos(self.heading), math.sin(self.heading)
        rotation = np.array([[cos_h, -sin_h], [sin_h, cos_h]])
        return np.array([self.x, self.y]) + local @ rotation.T

    def collides(self, step_height: float) -> bool:
        """True if a rock more than step_height tall (World.obstacle_mask's definition) lies under
        the footprint."""
        return bool(np.any(self.footprint_protrusion() > step_height))

    def clearance(self, step_height: float, reach: float, direction: int = 1) -> float:
        """How far the body can drive straight on (direction +1 forward, -1 backward) before its
        footprint covers a rock taller than step_height; 0 if it covers one now, inf beyond reach."""
        c, grid = self.config, self.world.grid
        half_l, half_w = c.body_length_m / 2, c.body_width_m / 2
        cos_h, sin_h = math.cos(self.heading), math.sin(self.heading)
        ahead = np.array([[-half_l, -half_w], [-half_l, half_w], [half_l + reach, -half_w], [half_l + reach, half_w]])
        ahead[:, 0] *= direction
        xs = self.x + cos_h * ahead[:, 0] - sin_h * ahead[:, 1]
        ys = self.y + sin_h * ahead[:, 0] + cos_h * ahead[:, 1]
        cols = np.arange(max(0, math.floor((xs.min() - grid.x_min) / grid.cell)),
                         min(grid.cols, math.ceil((xs.max() - grid.x_min) / grid.cell)) + 1)
        rows = np.arange(max(0, math.floor((ys.min() - grid.y_min) / grid.cell)),
                         min(grid.rows, math.ceil((ys.max() - grid.y_min) / grid.cell)) + 1)
        tall = self.world.protrusion_window(_span(rows), _span(cols)) > step_height
        if not tall.any():
            return math.inf
        x, y = grid.x_of(cols)[None, :], grid.y_of(rows)[:, None]
        along = ((x - self.x) * cos_h + (y - self.y) * sin_h) * direction
        across = -(x - self.x) * sin_h + (y - self.y) * cos_h
        inside = tall & (np.abs(across) <= half_w) & (along >= -half_l) & (along <= half_l + reach)
        if not inside.any():
            return math.inf
        return float(max(0.0, along[inside].min() - half_l))

    def footprint_protrusion(self) -> np.ndarray:
        """Rock protrusion at the world grid points under the body footprint."""
        grid = self.world.grid
        corners = self.footprint()
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        cols = np.arange(max(0, math.floor((lo[0] - grid.x_min) / grid.cell)),
                         min(grid.cols, math.ceil((hi[0] - grid.x_min) / grid.cell)) + 1)
        rows = np.arange(max(0, math.floor((lo[1] - grid.y_min) / grid.cell)),
                         min(grid.rows, math.ceil((hi[1] - grid.y_min) / grid.cell)) + 1)
        x, y = np.meshgrid(grid.x_of(cols), grid.y_of(rows))
        cos_h, sin_h = math.cos(self.heading), math.sin(self.heading)
        along = (x - self.x) * cos_h + (y - self.y) * sin_h
        across = -(x - self.x) * sin_h + (y - self.y) * cos_h
        c = self.config
        inside = (np.abs(along) <= c.body_length_m / 2) & (np.abs(across) <= c.body_width_m / 2)
        return self.world.protrusion_window(_span(rows), _span(cols))[inside]


def _settled_pose(contacts: np.ndarray) -> np.ndarray:
    """Body-to-world pose resting on four wheel contacts: origin at their mean, x along the
    rear-to-front direction, z normal to the plane they span (least-squares for four points)."""
    front_left, front_right, rear_left, rear_right = contacts
    forward = (front_left + front_right - rear_left - rear_right) / 2
    left = (front_left + rear_left - front_right - rear_right) / 2
    up = np.cross(forward, left)
    up /= np.linalg.norm(up)
    forward -= up * (forward @ up)
    forward /= np.linalg.norm(forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = forward, np.cross(up, forward), up
    pose[:3, 3] = contacts.mean(axis=0)
    return pose


def _seeded_mounts(config: RoverConfig) -> tuple[dict[str, SensorMount], dict[str, SensorMount]]:
    """True mounts (nominal + assembly error) and calibrated ones (true + calibration error)."""
    rng = np.random.default_rng([config.seed, 99])
    true, calibrated = {}, {}
    for name in sorted(config.mounts):   # sorted: the errors do not depend on dict order
        true[name] = _perturbed(config.mounts[name], config.assembly_error, rng)
        calibrated[name] = _perturbed(true[name], config.calibration_error, rng)
    return true, calibrated


def _perturbed(mount: SensorMount, error: MountError, rng: np.random.Generator) -> SensorMount:
    return SensorMount(
        position_m=tuple(float(v) for v in np.add(mount.position_m, rng.normal(0.0, error.translation_m, 3))),
        rotation_deg=tuple(float(v) for v in np.add(mount.rotation_deg, rng.normal(0.0, error.rotation_deg, 3))))


def _span(index: np.ndarray) -> slice:
    """The slice of a run of consecutive grid indices (empty for none)."""
    return slice(int(index[0]), int(index[-1]) + 1) if len(index) else slice(0, 0)
