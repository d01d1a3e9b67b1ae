"""What one simulated hop leaves behind: its images, their true poses, the truth and the rover's own sensors.

`HopRecord` is returned by `Hopper.hop` (hopper.py). `save(folder)` writes `frames.npz` (the images
and per-frame poses) and `hop.json` (the camera, the config and `truth()`); `HopRecord.load(folder)`
gives back an equal record. Inside: metres, seconds, radians, world x east / y north / z up, camera
frames as OpenCV. `truth()` is the human-facing dict: angles there are in degrees (`_deg` keys).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolbox.camera import Intrinsics

from .hopper_config import HopperConfig

FILE_FORMAT = "rvs-sim-hop/1"
FRAMES_FILE, TRUTH_FILE = "frames.npz", "hop.json"
IMAGE_FIELDS = ("frames", "timestamps", "camera_to_world", "before", "before_pose", "after", "after_pose")


@dataclass(frozen=True, eq=False)
class HopRecord:
    """One hop. Images are uint8 (h, w); without rendering the image arrays are empty ((0, h, w) frames,
    (0, 0) before / after) but times and poses are there."""

    config: HopperConfig
    camera: Intrinsics            # intrinsics of every frame
    camera_to_body: np.ndarray       # (4, 4) camera (OpenCV) to body; the body origin is the centre of mass
    seed: int | None                 # the hop's seed (None when a Generator was given)
    exposure_s: float | None         # the exposure used for every frame (None without rendering)
    # Images: in flight from launch (t = 0) to the first touchdown, at the frame rate.
    frames: np.ndarray               # (N, h, w) uint8
    timestamps: np.ndarray           # (N,) s after launch, the centre of each exposure
    camera_to_world: np.ndarray      # (N, 4, 4) true camera poses at the timestamps
    before: np.ndarray               # (h, w) uint8 at rest before launch, facing the hop
    before_pose: np.ndarray          # (4, 4)
    after: np.ndarray                # (h, w) uint8 at rest after the bounces
    after_pose: np.ndarray           # (4, 4)
    # The command.
    commanded_speed: float           # m/s
    commanded_elevation: float       # rad above the horizontal
    commanded_heading: float         # rad, counter-clockwise from east
    # The truth.
    launch_centre: np.ndarray        # (3,) centre of mass at launch
    launch_ground: np.ndarray        # (3,) ground point under it
    launch_yaw: float                # rad, the body's heading at launch (= the commanded heading)
    launch_velocity: np.ndarray      # (3,) m/s, the launch actually flown (with its errors)
    spin: np.ndarray                 # (3,) rad/s about the body axes during flight
    flight_time: float               # s from launch to the first touchdown
    landing_centre: np.ndarray       # (3,) centre of mass at the first touchdown
    landing_velocity: np.ndarray     # (3,) m/s arriving there
    contact_point: np.ndarray        # (3,) the surface point first touched
    contact_rock: int                # index into World.rocks of the rock touched; -1: the ground
    bounce_centres: np.ndarray       # (K, 3) centre of mass at each later touchdown
    settled_centre: np.ndarray       # (3,) centre of mass at rest after the bounces
    settled_ground: np.ndarray       # (3,) ground point under it: the hopper's new position
    settled_yaw: float               # rad, the body's heading at rest
    true_gravity_launch: np.ndarray  # (3,) unit gravity (down) in the camera frame at rest before launch
    true_gravity_settled: np.ndarray # (3,) the same after settling
    # The rover's own sensors (noisy).
    imu_gravity_launch: np.ndarray   # (3,) accelerometer's gravity direction in the camera frame
    imu_gravity_settled: np.ndarray  # (3,)
    sun_heading_launch: float        # rad, sun sensor's body heading before launch
    sun_heading_settled: float       # rad, after settling

    # ------------------------------------------------------------------------------ derived
    @property
    def launch_speed(self) -> float:
        return float(np.linalg.norm(self.launch_velocity))

    @property
    def launch_elevation(self) -> float:
        return float(math.atan2(self.launch_velocity[2], np.hypot(*self.launch_velocity[:2])))

    @property
    def launch_heading(self) -> float:
        return float(math.atan2(self.launch_velocity[1], self.launch_velocity[0]))

    @property
    def hop_range(self) -> float:
        """Horizontal distance flown by the centre of mass, launch to first touchdown."""
        return float(np.hypot(*(self.landing_centre - self.launch_centre)[:2]))

    @property
    def bounce_displacement(self) -> np.ndarray:
        """(3,) from the first touchdown to the rest position (centre of mass): what the rover cannot see."""
        return self.settled_centre - self.landing_centre

    @property
    def com_in_camera(self) -> np.ndarray:
        """(3,) the centre of mass in the camera frame (eq 1's offset, metres)."""
        rotation, position = self.camera_to_body[:3, :3], self.camera_to_body[:3, 3]
        return -rotation.T @ position

    # ------------------------------------------------------------------------------ truth
    def truth(self) -> dict:
        """Everything but the images and per-frame poses, JSON-able; angles in degrees."""
        deg = math.degrees
        return {
            "seed": self.seed,
            "exposure_ms": None if self.exposure_s is None else self.exposure_s * 1e3,
            "command": {"speed_mps": self.commanded_speed, "elevation_deg": deg(self.commanded_elevation),
                        "heading_deg": deg(self.commanded_heading)},
            "launch": {"centre_m": _list(self.launch_centre), "ground_m": _list(self.launch_ground),
                       "yaw_deg": deg(self.launch_yaw), "velocity_mps": _list(self.launch_velocity),
                       "speed_mps": self.launch_speed, "elevation_deg": deg(self.launch_elevation),
                       "heading_deg": deg(self.launch_heading), "spin_deg_s": _list(np.degrees(self.spin))},
            "flight": {"time_s": self.flight_time, "frames": int(len(self.timestamps)),
                       "range_m": self.hop_range},
            "landing": {"centre_m": _list(self.landing_centre), "velocity_mps": _list(self.landing_velocity),
                        "contact_point_m": _list(self.contact_point), "contact_rock": self.contact_rock},
            "bounces": {"centres_m": _list(self.bounce_centres),
                        "displacement_m": _list(self.bounce_displacement)},
            "settled": {"centre_m": _list(self.settled_centre), "ground_m": _list(self.settled_ground),
                        "yaw_deg": deg(self.settled_yaw)},
            "gravity_camera": {"launch": _list(self.true_gravity_launch),
                               "settled": _list(self.true_gravity_settled)},
            "sensors": {"imu_gravity_camera_launch": _list(self.imu_gravity_launch),
                        "imu_gravity_camera_settled": _list(self.imu_gravity_settled),
                        "sun_heading_launch_deg": deg(self.sun_heading_launch),
                        "sun_heading_settled_deg": deg(self.sun_heading_settled)},
        }

    # ------------------------------------------------------------------------------ save / load
    def save(self, folder: str | Path) -> Path:
        """Write the record into `folder` (made if missing): frames.npz and hop.json."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(folder / FRAMES_FILE, **{name: getattr(self, name) for name in IMAGE_FIELDS})
        document = {"format": FILE_FORMAT, "config": self.config.model_dump(mode="json"),
                    "camera": self.camera.as_dict(), "camera_to_body": _list(self.camera_to_body),
                    "truth": self.truth()}
        (folder / TRUTH_FILE).write_text(json.dumps(document, indent=1) + "\n")
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> HopRecord:
        folder = Path(folder)
        document = json.loads((folder / TRUTH_FILE).read_text())
        if document.get("format") != FILE_FORMAT:
            raise ValueError(f"{folder / TRUTH_FILE}: not a {FILE_FORMAT} file (format {document.get('format')!r})")
        with np.load(folder / FRAMES_FILE, allow_pickle=False) as data:
            images = {name: data[name] for name in IMAGE_FIELDS}
        return cls(config=HopperConfig.model_validate(document["config"]),
                   camera=Intrinsics(**document["camera"]),
                   camera_to_body=np.array(document["camera_to_body"]), **images,
                   **_fields_from_truth(document["truth"]))


def _fields_from_truth(truth: dict) -> dict:
    """The inverse of truth(): the record's stored (not derived) fields, in radians."""
    rad, a = math.radians, np.array
    launch, landing, settled, sensors = truth["launch"], truth["landing"], truth["settled"], truth["sensors"]
    exposure = truth["exposure_ms"]
    return {
        "seed": truth["seed"], "exposure_s": None if exposure is None else exposure * 1e-3,
        "commanded_speed": truth["command"]["speed_mps"],
        "commanded_elevation": rad(truth["command"]["elevation_deg"]),
        "commanded_heading": rad(truth["command"]["heading_deg"]),
        "launch_centre": a(launch["centre_m"]), "launch_ground": a(launch["ground_m"]),
        "launch_yaw": rad(launch["yaw_deg"]), "launch_velocity": a(launch["velocity_mps"]),
        "spin": np.radians(launch["spin_deg_s"]), "flight_time": truth["flight"]["time_s"],
        "landing_centre": a(landing["centre_m"]), "landing_velocity": a(landing["velocity_mps"]),
        "contact_point": a(landing["contact_point_m"]), "contact_rock": landing["contact_rock"],
        "bounce_centres": a(truth["bounces"]["centres_m"], dtype=np.float64).reshape(-1, 3),
        "settled_centre": a(settled["centre_m"]), "settled_ground": a(settled["ground_m"]),
        "settled_yaw": rad(settled["yaw_deg"]),
        "true_gravity_launch": a(truth["gravity_camera"]["launch"]),
        "true_gravity_settled": a(truth["gravity_camera"]["settled"]),
        "imu_gravity_launch": a(sensors["imu_gravity_camera_launch"]),
        "imu_gravity_settled": a(sensors["imu_gravity_camera_settled"]),
        "sun_heading_launch": rad(sensors["sun_heading_launch_deg"]),
        "sun_heading_settled": rad(sensors["sun_heading_settled_deg"]),
    }


def _list(values) -> list:
    return np.asarray(values, dtype=np.float64).tolist()
