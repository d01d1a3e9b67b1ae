"""Products for the web: the newest manifests, and one product's file, read safely.

Names are checked as the commands check them (protocol.check_safe_name): the product's name and every
part of the file's path must be a safe name, so `..`, absolute paths and hidden files never get as
far as the file system; the resolved file (symlinks followed) must still lie inside the product's
folder, so a link cannot lead out of the data directory.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rvs_server.protocol import check_safe_name

MAX_LIMIT = 200


class BadName(ValueError):
    """A name that is not a safe name (HTTP 400)."""


def newest_manifests(root: Path, limit: int) -> list[dict[str, Any]]:
    """The `limit` newest products' manifests (product.json), newest first; unreadable ones skipped."""
    found: list[tuple[float, Path]] = []
    for manifest in root.glob("*/product.json"):
        try:
            found.append((manifest.stat().st_mtime, manifest))
        except OSError:  # removed meanwhile
            continue
    found.sort(key=lambda item: item[0], reverse=True)
    manifests = []
    for _, path in found:
        if len(manifests) >= limit:
            break
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):  # being replaced, or removed by hand
            continue
        if isinstance(data, dict):
            data.setdefault("name", path.parent.name)
            manifests.append(data)
    return manifests


def product_file(root: Path, name: str, relative: str) -> Path | None:
    """The file `relative` of product `name`, or None when there is none; raises BadName."""
    parts = relative.split("/")
    for part in (name, *parts):
        try:
            check_safe_name(part)
        except ValueError as exc:
            raise BadName(str(exc)) from None
    folder = root / name
    try:
        base = folder.resolve(strict=True)
        target = folder.joinpath(*parts).resolve(strict=True)
    except (OSError, RuntimeError):  # missing, or a symlink loop
        return None
    if not target.is_relative_to(base) or not base.is_relative_to(root.resolve()) or not target.is_file():
        return None
    return target
