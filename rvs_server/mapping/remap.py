"""Re-map a stored acquisition with a changed workflow, with no device and no server.

A mapping product keeps its raw views and what the job knew (stored_views.py). `remap` loads them
as the results of the new workflow's acquisition steps (the engine's checkpoints: a step whose
result is there is not run), runs the rest of the workflow against an offline job that answers
what those steps ask of a job (the rover's pose, the calibration, the settings) from the stored
context, and writes a new product beside the source that names it in its manifest (`source`).
Nothing here opens a device, so it runs anywhere the files are: `rvs remap` sends each product to a
Dask worker (clients/remap.py).

Refused, before anything is written: a product without stored views, a workflow the engine
refuses, a workflow that acquires with another sensor than the stored views were taken with, and
one that merges the map before it (dem.merge_last: which map that was is not part of the views).
"""
from __future__ import annotations

import json
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rvs_server.app import load_module_config
from rvs_server.devices.calibration import Calibration
from rvs_server.products.manifests import Products
from rvs_server.workflow import WorkflowError, load_workflow, resolve_params, run_workflow
from toolbox.geometry import RoverPose

from .commands import MappingSettings, WorkflowArgs, module, note_fusion, write_maps
from .steps import operations
from .stored_views import ACQUISITION_OPS, FOLDER, NoStoredViews, keep_views, load_views, stored_key

UNSUPPORTED_OPS = {"dem.merge_last": "it merges the map made before the source, which its views do not hold"}


class RemapError(ValueError):
    """Why a product cannot be re-mapped with a workflow; nothing was written."""


@dataclass(frozen=True)
class _Rover:
    pose_estimate: RoverPose


@dataclass(frozen=True)
class _Devices:
    rover: _Rover
    truth: None = None          # no simulator: the source's truth is copied where the grid is the same
    simulated: bool = False


@dataclass(frozen=True)
class _Server:
    stored_calibration: Calibration

    def calibration(self) -> Calibration:
        return self.stored_calibration


@dataclass
class OfflineJob:
    """What the mapping steps after the acquisition use of a JobContext, answered from stored views."""

    server: _Server
    devices: _Devices
    settings: MappingSettings
    on_progress: Callable[[float, str], None] | None = None
    messages: list[str] = field(default_factory=list)

    def progress(self, percent: float, message: str) -> None:
        if self.on_progress is not None:
            self.on_progress(percent, message)

    def safe_point(self) -> None:
        """No break to honour: a Dask task is cancelled from outside."""

    def native(self, step: str, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        # In the worker's own process already: a crash there is the task's, not a server's.
        return func(*args, **kwargs)

    def settings_of(self, name: str) -> Any:
        if name != "mapping":
            raise RemapError(f"a step asked for the {name} settings, which a remap has not")
        return self.settings


def remap(source: str | Path, workflow_file: str | Path, data_dir: str | Path | None = None,
          config_dir: str | Path | None = None, name: str | None = None,
          on_progress: Callable[[float, str], None] | None = None) -> dict[str, Any]:
    """Run `workflow_file` on the stored views of the product folder `source`; the new product goes to
    `data_dir`/products (default: beside the source). `config_dir`: take the mapping settings
    ($config) from its mapping.toml instead of those the source was made with. Returns the new
    product's name and path and the map's summary (cells, known, hazardous)."""
    source = Path(source).resolve()
    if not (source / "product.json").is_file():
        raise RemapError(f"{source}: not a product folder (no product.json)")
    try:
        stored = load_views(source)
    except NoStoredViews as exc:
        raise RemapError(str(exc)) from None
    try:
        workflow = load_workflow(Path(workflow_file), operations, WorkflowArgs, MappingSettings)
    except (WorkflowError, OSError) as exc:
        raise RemapError(f"workflow refused: {exc}") from None
    for step in workflow.steps:
        if step.op in UNSUPPORTED_OPS:
            raise RemapError(f"{workflow.path.name}: step {step.name} ({step.op}) cannot run on stored views: "
                             f"{UNSUPPORTED_OPS[step.op]}")
        if step.op in ACQUISITION_OPS and step.op not in stored.results:
            raise RemapError(f"{workflow.path.name}: step {step.name} ({step.op}) needs views that {source.name} "
                             f"did not store (it holds {', '.join(sorted(stored.results))})")
    settings = (load_module_config(Path(config_dir), module).settings if config_dir is not None
                else MappingSettings(**stored.settings))
    args = WorkflowArgs(**stored.args)
    try:
        params = resolve_params(workflow, operations, args, settings)
    except WorkflowError as exc:
        raise RemapError(f"{workflow.path.name}: {exc}") from None

    manifest = json.loads((source / "product.json").read_text())
    products = Products(Path(data_dir) if data_dir is not None else source.parent.parent)
    product = products.create(stored.command, name or f"{source.name}-remap", manifest.get("arguments", {}),
                              manifest.get("config"))
    job = OfflineJob(_Server(stored.calibration), _Devices(_Rover(stored.pose)), settings, on_progress)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="rvs-remap-") as scratch:
        checkpoints = Path(scratch)
        for step in workflow.steps:        # the stored acquisition stands in for the steps that used devices
            if step.op in ACQUISITION_OPS:
                for suffix in (".npz", ".json"):
                    shutil.copyfile(source / FOLDER / f"{stored_key(step.op)}{suffix}",
                                    checkpoints / f"{step.name}{suffix}")
        results, provenance = run_workflow(workflow, operations, params, job, checkpoints)  # type: ignore[arg-type]
    for record in provenance:
        if "seconds" in record:
            product.timing(record["step"], record["seconds"])
    product.note("workflow", {"file": str(workflow.path), "name": workflow.name, "sha256_16": workflow.digest,
                              "steps": provenance, "args": args.model_dump(mode="json")})
    product.note("source", {"product": source.name, "path": str(source), "command": stored.command,
                            "created": manifest.get("created"),
                            "workflow": (manifest.get("workflow") or {}).get("sha256_16"),
                            "settings": "config dir " + str(config_dir) if config_dir else "the source's"})
    summary = write_maps(job, product, results, settings)  # type: ignore[arg-type]
    note_fusion(product, results, summary)
    _copy_truth(source, product)
    keep_views(product, workflow, results, stored.pose, stored.calibration, settings, args, stored.command)
    product.timing("total", time.perf_counter() - started)
    product.finish()
    return {"product": product.name, "path": str(product.path), "source": source.name, **summary}


def _copy_truth(source: Path, product: Any) -> None:
    """The source's truth grids, where the new map has the same grid (the simulator is not here)."""
    try:
        same = json.loads((source / "grid.json").read_text()) == json.loads((product.path / "grid.json").read_text())
    except (OSError, ValueError):
        return
    if not same or not (source / "truth").is_dir():
        return
    described = json.loads((source / "product.json").read_text()).get("files", {})
    for path in sorted((source / "truth").rglob("*")):
        if path.is_file():
            relative = path.relative_to(source).as_posix()
            shutil.copyfile(path, product.add(relative, described.get(relative, "truth (copied from the source)")))
