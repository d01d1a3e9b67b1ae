"""The test bed's calibration: where each sensor sits on the PTU head, where the PTU sits on the
rover, the cameras' intrinsics and the rover's body, as the mapping chain needs them.

`configs/calibration.toml` holds a real calibration. With simulated devices, `source = "simulator"`
takes the simulator's *calibrated* mounts instead: what a calibration of the simulated rover would
have found, slightly off its true (rendered) mounts, so maps carry a realistic calibration error.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from pydantic import Field

from rvs_server.config import Settings
from toolbox.camera import Intrinsics
from toolbox.geometry import SensorMount

Vector = tuple[float, float, float]


class MountCalibration(Settings):
    position_m: Vector = Field(..., description="optical centre in the PTU head frame, metres")
    rotation_deg: Vector = Field((0.0, 0.0, 0.0), description="roll, pitch, yaw away from head x, degrees")


class IntrinsicsCalibration(Settings):
    width: int = Field(..., gt=0)
    height: int = Field(..., gt=0)
    fx: float = Field(..., gt=0)
    fy: float = Field(..., gt=0)
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0


def _default_mounts() -> dict[str, MountCalibration]:
    return {"left": MountCalibration(position_m=(0.05, 0.125, 0.08)),
            "right": MountCalibration(position_m=(0.05, -0.125, 0.08)),
            "tof": MountCalibration(position_m=(0.07, 0.0, 0.03))}


class CalibrationConfig(Settings):
    source: Literal["simulator", "file"] = Field(
        "simulator", description="simulator: the simulated rover's calibrated mounts; file: the values below")
    ptu_position_m: Vector = Field((0.10, 0.0, 1.40), description="pan/tilt axes' crossing in the rover frame")
    mounts: dict[str, MountCalibration] = Field(default_factory=_default_mounts)
    tof_intrinsics: IntrinsicsCalibration = IntrinsicsCalibration(
        width=176, height=144, fx=262.92, fy=262.92, cx=88.0, cy=69.0, k1=-0.826, k2=0.656)
    rover_length_m: float = Field(0.55, gt=0, description="body footprint, for removing the rover from maps")
    rover_width_m: float = Field(0.50, gt=0)


@dataclass(frozen=True)
class Calibration:
    """What the mapping chain uses: toolbox mounts and intrinsics."""

    mounts: dict[str, SensorMount]
    tof_intrinsics: Intrinsics
    rover_length_m: float
    rover_width_m: float
    source: str


def build_calibration(config: CalibrationConfig, testbed: Any = None) -> Calibration:
    ptu = config.ptu_position_m
    if config.source == "simulator" and testbed is not None:
        rover = testbed.rover
        ptu = tuple(rover.config.ptu_position_m)
        mounts = {name: SensorMount.from_offsets(ptu, m.position_m, m.rotation_deg)
                  for name, m in rover.calibrated_mounts.items()}
        length, width = rover.config.body_length_m, rover.config.body_width_m
    else:
        mounts = {name: SensorMount.from_offsets(ptu, m.position_m, m.rotation_deg)
                  for name, m in config.mounts.items()}
        length, width = config.rover_length_m, config.rover_width_m
    return Calibration(mounts=mounts, tof_intrinsics=Intrinsics(**config.tof_intrinsics.model_dump()),
                       rover_length_m=length, rover_width_m=width, source=config.source)
