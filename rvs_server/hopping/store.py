"""The files of the hopping commands' products: a hop as the rover recorded it (apart from the
simulator's truth), a reconstruction, and coloured point clouds as PLY.

A `hop-NNN` product holds what a real hopper would hand over, and nothing more:
    frames.npz     frames (N, h, w) uint8, timestamps (N,) s after launch, before / after (at rest)
    hop.json       the command, the camera's calibration (intrinsics, camera-to-body), the body radius
    sensors.json   the accelerometer's gravity direction and the sun sensor's heading, at rest
and, simulated, truth/hop.json (drivers.sim HopRecord.truth(): launch, landing, bounces, rest) and
truth/poses.npz (true per-frame camera poses). hop-plan reads only the first three, so it runs the
same on a real hop's files.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rvs_server.files import save_npz_atomic
from rvs_server.hopping.sfm import HopReconstruction
from toolbox.camera import Intrinsics

HOP_FORMAT = "rvs-hop/1"
HOP_NAME = re.compile(r"hop-(\d{3,})")


@dataclass(frozen=True)
class HopObservation:
    """One hop as the rover itself knows it (loaded from a hop product)."""

    name: str
    frames: np.ndarray            # (N, h, w) uint8
    timestamps: np.ndarray        # (N,) s after launch
    camera: Intrinsics
    camera_to_body: np.ndarray    # (4, 4) camera (OpenCV axes) to body (x forward, y left, z up)
    body_radius: float            # m: the body rests this high on its centre
    command: dict                 # speed_mps, elevation_deg, heading_deg
    gravity_launch: np.ndarray    # (3,) accelerometer's unit gravity (down) in the camera frame, before launch
    sun_heading_launch: float     # rad, the sun sensor's body heading before launch

    @property
    def com_in_camera(self) -> np.ndarray:
        """The centre of mass in the camera frame (eq 1's offset, metres)."""
        rotation, position = self.camera_to_body[:3, :3], self.camera_to_body[:3, 3]
        return -rotation.T @ position

    @property
    def frame_interval(self) -> float:
        return float(np.median(np.diff(self.timestamps))) if len(self.timestamps) > 1 else 0.0


# ------------------------------------------------------------------------------------ hop products
def next_hop_number(products_root: Path) -> int:
    """1 + the highest hop-NNN product number already in the data directory, so numbers never repeat."""
    numbers = [int(m.group(1)) for p in products_root.iterdir() if (m := HOP_NAME.fullmatch(p.name))]
    return max(numbers, default=0) + 1


def write_hop(product: Any, record: Any, number: int) -> None:
    """A simulated HopRecord into a hop product: the rover's view at the top, the truth in truth/."""
    save_npz_atomic(product.add("frames.npz", "frames (N, h, w) uint8 from launch to the first touchdown, "
                                "timestamps (N,) s after launch, before / after: at rest"),
                    {"frames": record.frames, "timestamps": record.timestamps, "before": record.before,
                     "after": record.after}, compressed=True)
    product.write_json("hop.json", {
        "format": HOP_FORMAT, "hop": number,
        "command": {"speed_mps": record.commanded_speed, "elevation_deg": math.degrees(record.commanded_elevation),
                    "heading_deg": math.degrees(record.commanded_heading)},
        "frames": int(len(record.frames)), "last_frame_s": float(record.timestamps[-1]),
        "exposure_ms": None if record.exposure_s is None else record.exposure_s * 1e3,
        "camera": record.camera.as_dict(), "camera_to_body": record.camera_to_body.tolist(),
        "body_radius_m": record.config.body_radius_m,
        "frames_note": "camera frame as OpenCV; body x forward, y left, z up, origin at the centre of mass",
    }, "the hop command and the hopper's calibration: camera intrinsics, camera-to-body, body radius")
    product.write_json("sensors.json", {
        "imu_gravity_camera_launch": record.imu_gravity_launch.tolist(),
        "imu_gravity_camera_settled": record.imu_gravity_settled.tolist(),
        "sun_heading_launch_deg": math.degrees(record.sun_heading_launch),
        "sun_heading_settled_deg": math.degrees(record.sun_heading_settled),
        "note": "accelerometer: unit gravity (down) in the camera frame at rest; sun sensor: the body's heading, "
                "degrees counter-clockwise from east; before launch and after settling",
    }, "the attitude sensors' readings at rest before launch and after settling (noisy)")
    product.write_json("truth/hop.json", {"config": record.config.model_dump(mode="json"), "truth": record.truth()},
                       "simulator truth of the hop: launch actually flown, first touchdown, bounces, rest "
                       "(drivers/sim/hopper_record.py truth())")
    save_npz_atomic(product.add("truth/poses.npz", "true camera-to-world poses: camera_to_world (N, 4, 4), "
                                "before_pose, after_pose"),
                    {"camera_to_world": record.camera_to_world, "before_pose": record.before_pose,
                     "after_pose": record.after_pose}, compressed=True)


def load_observation(folder: Path) -> HopObservation:
    """A hop product's frames, calibration and sensor readings (never its truth)."""
    document = json.loads((folder / "hop.json").read_text())
    if document.get("format") != HOP_FORMAT:
        raise ValueError(f"{folder / 'hop.json'}: not a {HOP_FORMAT} file")
    sensors = json.loads((folder / "sensors.json").read_text())
    with np.load(folder / "frames.npz", allow_pickle=False) as data:
        frames, timestamps = data["frames"], data["timestamps"]
    camera = document["camera"]
    return HopObservation(
        name=folder.name, frames=frames, timestamps=timestamps,
        camera=Intrinsics(**{k: camera[k] for k in ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2")}),
        camera_to_body=np.array(document["camera_to_body"]), body_radius=float(document["body_radius_m"]),
        command=document["command"], gravity_launch=np.array(sensors["imu_gravity_camera_launch"]),
        sun_heading_launch=math.radians(sensors["sun_heading_launch_deg"]))


def load_truth(folder: Path) -> dict | None:
    """A simulated hop's truth (HopRecord.truth()), or None for a hop without one."""
    path = folder / "truth" / "hop.json"
    return json.loads(path.read_text())["truth"] if path.exists() else None


# ------------------------------------------------------------------------------------ reconstruction
def save_reconstruction(path: Path, sfm: HopReconstruction) -> None:
    fields = {k: v for k, v in asdict(sfm).items() if k != "timings"}
    save_npz_atomic(path, {**fields, "timings": json.dumps(sfm.timings)}, compressed=True)


def load_reconstruction(path: Path) -> HopReconstruction:
    with np.load(path, allow_pickle=False) as data:
        fields = {k: data[k] for k in data.files if k != "timings"}
        timings = json.loads(str(data["timings"]))
    fields["reprojection_error"] = float(fields["reprojection_error"])
    fields["num_models"] = int(fields["num_models"])
    return HopReconstruction(**fields, timings=timings)


# ------------------------------------------------------------------------------------ PLY
def cloud_of(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) float64, colours (N, 3) uint8 or None) of PLY vertices."""
    points = np.column_stack([vertices[k].astype(np.float64) for k in "xyz"])
    names = vertices.dtype.names or ()
    colours = np.column_stack([vertices[k] for k in ("red", "green", "blue")]) if "red" in names else None
    return points, colours
