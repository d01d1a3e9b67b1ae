"""A mapping product's stored views: what the devices gave (the planned views, the raw frames with
their PTU angles and camera poses) and what the job knew (the rover's pose, the calibration, the
mapping settings, the command's arguments). With them, `rvs remap` runs a changed workflow on the
same acquisition later, with no device (rvs_server/mapping/remap.py).

In the product: views/<op>.npz and .json for each acquisition step (views_plan, acquire_tof or
acquire_stereo; the workflow engine's own checkpoint format, compressed) and views/context.json.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rvs_server.devices.calibration import Calibration
from rvs_server.workflow import Workflow, has_result, load_result, save_result
from toolbox.camera import Intrinsics
from toolbox.geometry import RoverPose, SensorMount

from .steps import operations

ACQUISITION_OPS = ("views.plan", "acquire.tof", "acquire.stereo")   # the steps that use devices
FOLDER = "views"
CONTEXT = f"{FOLDER}/context.json"


def stored_key(op: str) -> str:
    return op.replace(".", "_")


def keep_views(product: Any, workflow: Workflow, results: dict[str, Any], pose: RoverPose,
               calibration: Calibration, settings: Any, args: Any, command: str) -> None:
    """Store the acquisition steps' results and the job's context in the product."""
    kept = []
    for step in workflow.steps:
        if step.op in ACQUISITION_OPS and step.name in results:
            key = stored_key(step.op)
            folder = product.add(f"{FOLDER}/{key}.npz", f"stored result of the {step.op} step (raw views, "
                                 "for rvs remap)").parent
            product.add(f"{FOLDER}/{key}.json", f"the structure of {key}.npz")
            save_result(folder, key, results[step.name], operations.types, compressed=True)
            kept.append(step.op)
    product.write_json(CONTEXT, {
        "command": command, "steps": kept, "rover_pose": dataclasses.asdict(pose),
        "calibration": calibration_to_json(calibration), "settings": settings.model_dump(mode="json"),
        "args": args.model_dump(mode="json")},
        "what the job knew when it acquired the views: rover pose, calibration, mapping settings, arguments")


@dataclass(frozen=True)
class StoredViews:
    source: Path
    command: str
    results: dict[str, Any]       # by acquisition op
    pose: RoverPose
    calibration: Calibration
    settings: dict[str, Any]
    args: dict[str, Any]


class NoStoredViews(ValueError):
    """A product without stored views (not a mapping product, or made before views were kept)."""


def load_views(product_dir: Path) -> StoredViews:
    context_file = product_dir / CONTEXT
    if not context_file.is_file():
        raise NoStoredViews(f"{product_dir.name}: no stored views ({CONTEXT} missing): only dem-full-tof, "
                            "dem-update-tof, dem-full and dem-update products keep theirs, since 2026-12-06")
    context = json.loads(context_file.read_text())
    folder = product_dir / FOLDER
    results = {}
    for op in context["steps"]:
        key = stored_key(op)
        if not has_result(folder, key):
            raise NoStoredViews(f"{product_dir.name}: {FOLDER}/{key}.npz or .json missing")
        results[op] = load_result(folder, key, operations.types)
    return StoredViews(product_dir, context["command"], results, RoverPose(**context["rover_pose"]),
                       calibration_from_json(context["calibration"]), context["settings"], context["args"])


def calibration_to_json(calibration: Calibration) -> dict[str, Any]:
    return {"mounts": {name: {"ptu_position": list(m.ptu_position),
                              "camera_to_head": np.asarray(m.camera_to_head).tolist()}
                       for name, m in calibration.mounts.items()},
            "tof_intrinsics": dataclasses.asdict(calibration.tof_intrinsics),
            "rover_length_m": calibration.rover_length_m, "rover_width_m": calibration.rover_width_m,
            "source": calibration.source}


def calibration_from_json(data: dict[str, Any]) -> Calibration:
    mounts = {name: SensorMount(tuple(m["ptu_position"]), np.asarray(m["camera_to_head"], dtype=np.float64))
              for name, m in data["mounts"].items()}
    return Calibration(mounts=mounts, tof_intrinsics=Intrinsics(**data["tof_intrinsics"]),
                       rover_length_m=data["rover_length_m"], rover_width_m=data["rover_width_m"],
                       source=data["source"])
