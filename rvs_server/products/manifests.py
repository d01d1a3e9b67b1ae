"""Product folders: every result lives in `<data>/products/<name>/` with a `product.json` manifest.

The manifest says what made the product (command, arguments, configuration snapshot, workflow,
inputs, timings, software version) so anyone can tell where a file came from. Names are client
given but are names, not paths; an existing product is never overwritten: a second `--output run`
becomes `run-2`. When devices are simulated, the simulator's truth for that moment goes to a
`truth/` subfolder, apart from what the sensors saw.
"""
from __future__ import annotations

import json
import platform
import re
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rvs_server import __version__
from rvs_server.files import write_json_atomic
from rvs_server.products.ply import ply_summary
from rvs_server.products.rasters import geotiff_grid
from rvs_server.protocol import BadRequest, check_safe_name


class Product:
    """One product folder being written; `finish()` writes the manifest last."""

    def __init__(self, path: Path, name: str, command: str, arguments: Mapping[str, Any],
                 config: Mapping[str, Any] | None = None, job: str | None = None):
        self.path = path
        self.name = name
        self.finished = False
        self.manifest: dict[str, Any] = {
            "name": name,
            "command": command,
            "arguments": dict(arguments),
            "config": dict(config or {}),
            "job": job,
            "software": {"rvs": __version__, "python": platform.python_version(), "numpy": np.__version__},
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "inputs": [],
            "timings_s": {},
            "files": {},
        }
        manifest = path / "product.json"
        if manifest.exists():  # a continued job writes on into its own folder
            previous = json.loads(manifest.read_text())
            self.manifest["files"] = previous.get("files", {})
            self.manifest["timings_s"] = previous.get("timings_s", {})
            self.manifest["created"] = previous.get("created", self.manifest["created"])

    def file(self, relative: str) -> Path:
        """A path inside the product for `relative` (which may name a subfolder, e.g. truth/x.tif)."""
        parts = Path(relative).parts
        if not parts or any(p in ("..", "") or p.startswith(".") for p in parts) or Path(relative).is_absolute():
            raise ValueError(f"{relative!r} is not a file name inside a product")
        target = self.path.joinpath(*parts)
        target.parent.mkdir(parents=True, exist_ok=True)
        return target

    def add(self, relative: str, description: str) -> Path:
        """Register a file with what it holds; the caller writes it, through rvs_server.files so that a
        kill never leaves half of it."""
        self.manifest["files"][relative] = description
        return self.file(relative)

    def write_json(self, relative: str, data: Any, description: str) -> Path:
        return write_json_atomic(self.add(relative, description), data, default=_jsonable)

    def timing(self, step: str, seconds: float) -> None:
        self.manifest["timings_s"][step] = round(float(seconds), 4)

    def note(self, key: str, value: Any) -> None:
        self.manifest[key] = value

    def finish(self, status: str = "complete") -> Path:
        """Write the manifest. Status: complete, interrupted (continue finishes it) or failed."""
        self.finished = True
        self.manifest["status"] = status
        grids = self._grids()
        if grids:
            self.manifest["grids"] = grids
        clouds = self._clouds()
        if clouds:
            self.manifest["clouds"] = clouds
        self.manifest["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        return write_json_atomic(self.path / "product.json", self.manifest, default=_jsonable)


    def _grids(self) -> dict[str, dict[str, Any]]:
        """Where each GeoTIFF lies in the world, so a viewer can place maps, paths and markers without
        opening the files: origin (south-west corner), cell, rows, cols, frame. Rows count northwards;
        the files and pictures show them north up."""
        grids = {}
        for relative in self.manifest["files"]:
            if not relative.endswith((".tif", ".tiff")):
                continue
            try:
                spec = geotiff_grid(self.path / relative)
            except (OSError, ValueError, IndexError, KeyError):  # not written (yet), or not a GeoTIFF
                continue
            if spec is not None:
                grids[relative] = {"origin": [round(spec.origin_x, 6), round(spec.origin_y, 6)],  # to the micrometre
                                   "cell": round(spec.cell, 6), "rows": spec.rows, "cols": spec.cols, "frame": "world"}
        return grids

    def _clouds(self) -> dict[str, dict[str, Any]]:
        """What each PLY cloud holds, so a reader can check it opened the whole cloud: points (the vertex
        count) and min, max (each [x, y, z], metres, world frame, to the micrometre)."""
        clouds = {}
        for relative in self.manifest["files"]:
            if not relative.endswith(".ply"):
                continue
            try:
                summary = ply_summary(self.path / relative)
            except (OSError, ValueError, KeyError):  # not written (yet), or not a PLY of ours
                continue
            if summary is not None:
                clouds[relative] = summary
        return clouds


class ProductPart:
    """A sub-folder of a product that takes files like a product: everything goes under FOLDER/ and
    into the one manifest (navigate keeps each cycle's maps this way)."""

    def __init__(self, product: Product, folder: str):
        self.product, self.folder = product, folder
        self.name, self.path = product.name, product.path

    def add(self, relative: str, description: str) -> Path:
        return self.product.add(f"{self.folder}/{relative}", description)

    def write_json(self, relative: str, data: Any, description: str) -> Path:
        return self.product.write_json(f"{self.folder}/{relative}", data, description)

    def file(self, relative: str) -> Path:
        return self.product.file(f"{self.folder}/{relative}")

    def timing(self, step: str, seconds: float) -> None:
        self.product.timing(f"{self.folder}/{step}", seconds)

    def note(self, key: str, value: Any) -> None:
        self.product.note(f"{self.folder}/{key}", value)


class Products:
    """Where products go, and how their names are chosen."""

    def __init__(self, data_dir: Path):
        self.root = data_dir / "products"
        self.root.mkdir(parents=True, exist_ok=True)

    def create(self, command: str, name: str | None, arguments: Mapping[str, Any],
               config: Mapping[str, Any] | None = None, job: str | None = None) -> Product:
        """A new folder named `name` (or COMMAND-TIME), with a suffix when the name is taken."""
        base = name or f"{command}-{time.strftime('%Y%m%d-%H%M%S')}"
        try:
            check_safe_name(base)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        chosen = base
        for index in range(2, 10000):
            try:
                (self.root / chosen).mkdir()
                break
            except FileExistsError:
                chosen = f"{base}-{index}"
        else:
            raise BadRequest(f"too many products named {base}")
        return Product(self.root / chosen, chosen, command, arguments, config, job)

    def reopen(self, name: str, command: str, arguments: Mapping[str, Any],
               config: Mapping[str, Any] | None = None, job: str | None = None) -> Product:
        """The folder of an interrupted job, so `continue` finishes the same product."""
        check_safe_name(name)
        path = self.root / name
        path.mkdir(parents=True, exist_ok=True)
        return Product(path, name, command, arguments, config, job)

    def latest(self, command_pattern: str, where: Callable[[dict], bool] | None = None,
               statuses: tuple[str, ...] = ("complete",)) -> Product | None:
        """The most recent product in one of `statuses` made by a command matching the pattern (and whose
        manifest satisfies `where`)."""
        pattern = re.compile(command_pattern)
        best: tuple[float, Path] | None = None
        for manifest in self.root.glob("*/product.json"):
            try:
                data = json.loads(manifest.read_text())
            except (OSError, ValueError):
                continue
            if data.get("status") in statuses and pattern.fullmatch(data.get("command", "")) and \
                    (where is None or where(data)):
                mtime = manifest.stat().st_mtime
                if best is None or mtime > best[0]:
                    best = (mtime, manifest.parent)
        if best is None:
            return None
        data = json.loads((best[1] / "product.json").read_text())
        product = Product(best[1], best[1].name, data["command"], data.get("arguments", {}), data.get("config"))
        product.manifest = data
        return product


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (tuple, set)):
        return list(value)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON")
