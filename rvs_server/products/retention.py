"""Keeping the disk: what products there are, which must stay, the retention rule, the storage cap.

A season of jobs piles products up. The rule (server.toml `[storage]`): at most `max_gib` GiB and
`max_days` days of products, removed oldest first, but never a product that something still needs
(`protected_products`): one a recovery set names (the job `continue` would finish, or an input it
reads), a route's own product (data/routes), an input of the hop map (the hops and hop-plans whose
clouds hop-map merges, in this server's memory and in the newest hop-map product), one a running job
is writing, one still being written without a manifest since this server started (an activity's),
and the newest product of each command.

The cap (`cap_gib`) is a hard limit on the products folder that every atomic write checks
(rvs_server/files.py): a write that would take it past the cap fails with ENOSPC, exactly as a full
disk would, so the job runner's one ENOSPC path (ERR 507 storage) is exercised without a small disk.
"""
from __future__ import annotations

import errno
import json
import logging
import os
import re
import shutil
import sqlite3
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rvs_server import files
from rvs_server.server_config import StorageSettings

if TYPE_CHECKING:
    from rvs_server.host import Host

log = logging.getLogger("rvs.storage")

GIB = 1024 ** 3
DAY_S = 86400.0


@dataclass
class ProductInfo:
    name: str
    path: Path
    command: str          # from the manifest; "" when it has none (yet)
    status: str           # complete | interrupted | failed | writing (no manifest)
    bytes: int
    mtime: float          # the newest file's modification time: when the product was last written

    def age_days(self, now: float) -> float:
        return max(0.0, (now - self.mtime) / DAY_S)


def list_products(root: Path) -> list[ProductInfo]:
    """Every product folder under `root` (data/products), oldest first."""
    infos = []
    try:
        entries = list(os.scandir(root))
    except FileNotFoundError:
        return []
    for entry in entries:
        if not entry.is_dir(follow_symlinks=False) or entry.name.startswith("."):
            continue
        path = Path(entry.path)
        size, newest = _size_and_mtime(path)
        command, status = "", "writing"
        try:
            manifest = json.loads((path / "product.json").read_text())
            command, status = str(manifest.get("command", "")), str(manifest.get("status", "complete"))
        except (OSError, ValueError):
            pass
        infos.append(ProductInfo(entry.name, path, command, status, size, newest))
    return sorted(infos, key=lambda p: (p.mtime, p.name))


def _size_and_mtime(folder: Path) -> tuple[int, float]:
    size, newest = 0, 0.0
    for base, _, names in os.walk(folder):
        try:
            newest = max(newest, os.stat(base).st_mtime)
        except FileNotFoundError:
            continue
        for name in names:
            try:
                info = os.stat(os.path.join(base, name))
            except FileNotFoundError:
                continue
            size += info.st_size
            newest = max(newest, info.st_mtime)
    return size, newest


# ------------------------------------------------------------------------------------------------
# What must stay


def protected_products(server: Host, infos: list[ProductInfo] | None = None) -> dict[str, str]:
    """The names of the products the retention rule must never remove, each with why."""
    root = server.products.root
    infos = list_products(root) if infos is None else infos
    names = {p.name for p in infos}
    keep: dict[str, str] = {}

    def protect(name: str, why: str) -> None:
        if name in names and name not in keep:
            keep[name] = why

    # Recovery sets: the product a continued job writes on into (state["product"]) and every input it
    # names (hop-plan's hop and previous plan, a cloud's path), anywhere in its state or options.
    for rset in server.recovery.all():
        for name in _named_products({"state": rset.state, "options": rset.options}, names, root):
            protect(name, f"recovery:{rset.job}")
    # A running job: the products it has opened so far.
    job = server.dispatcher.job
    if job is not None:
        for name in job.products:
            protect(name, f"job:{job.id}")
    # Routes (data/routes): each finished route's own product, route-NAME (or route-NAME-N).
    for route in _route_names(server.data_dir / "routes"):
        pattern = re.compile(re.escape(f"route-{route}") + r"(-\d+)?")
        for info in infos:
            if info.command in ("route-record", "") and pattern.fullmatch(info.name):
                protect(info.name, f"route:{route}")
    # The hop map: the hops and hop-plans (their clouds) hop-map merges, as this server knows them ...
    for entry in _hop_entries(server):
        for value in (getattr(entry, "product", None), getattr(entry, "plan", None), getattr(entry, "cloud", None)):
            for name in _named_products(value, names, root):
                protect(name, "hop-map")
    # ... and as the newest hop-map product lists them (after a restart the memory is empty).
    hop_maps = [p for p in infos if p.command == "hop-map"]
    if hop_maps:
        try:
            manifest = json.loads((hop_maps[-1].path / "product.json").read_text())
        except (OSError, ValueError):
            manifest = {}
        for name in _named_products(manifest.get("inputs"), names, root):
            protect(name, "hop-map")
    # Written now without a manifest (a job's or an activity's product in this run).
    started_wall = time.time() - (time.monotonic() - server.started)
    for info in infos:
        if info.status == "writing" and info.mtime >= started_wall:
            protect(info.name, "writing")
    # The newest of each command.
    newest: dict[str, ProductInfo] = {}
    for info in infos:
        if info.command:
            newest[info.command] = info  # infos are oldest first
    for command, info in newest.items():
        protect(info.name, f"newest:{command}")
    return keep


def _named_products(value: Any, names: set[str], root: Path) -> Iterable[str]:
    """Product names that `value` (JSON-like) mentions: a string equal to a name, or a path inside one."""
    if isinstance(value, str):
        if value in names:
            yield value
        elif os.sep in value:
            try:
                relative = Path(value).resolve().relative_to(root.resolve())
            except (ValueError, OSError):
                return
            if relative.parts and relative.parts[0] in names:
                yield relative.parts[0]
    elif isinstance(value, dict):
        for item in value.values():
            yield from _named_products(item, names, root)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _named_products(item, names, root)


def _route_names(directory: Path) -> list[str]:
    """The routes in the route store, read-only (the routes package owns the database)."""
    database = directory / "routes.sqlite"
    if not database.exists():
        return []
    try:
        with sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=5) as connection:
            return [row[0] for row in connection.execute("SELECT name FROM routes")]
    except sqlite3.Error as exc:
        log.warning("retention: cannot read the routes in %s (%s); route products are all kept", database, exc)
        return ["*"]  # unreadable: keep every route product rather than guess


def _hop_entries(server: Host) -> list[Any]:
    """The hops the hopping module holds in memory (read by name: the core imports no capability)."""
    if "hopping" not in server.registry.modules:
        return []
    try:
        state = server.state_of("hopping")
    except KeyError:
        return []
    return list(getattr(state, "hops", []) or [])


# ------------------------------------------------------------------------------------------------
# The rule


@dataclass
class PruneReport:
    removed: list[ProductInfo]
    kept_bytes: int
    total_bytes: int
    protected: dict[str, str]
    dry_run: bool

    @property
    def freed_bytes(self) -> int:
        return sum(p.bytes for p in self.removed)


def choose(settings: StorageSettings, infos: list[ProductInfo], protected: dict[str, str],
           now: float | None = None) -> list[ProductInfo]:
    """What the rule removes: every unprotected product older than max_days, then the oldest
    unprotected ones until the total is at most max_gib."""
    now = time.time() if now is None else now
    candidates = [p for p in infos if p.name not in protected]  # oldest first
    chosen: list[ProductInfo] = []
    if settings.max_days > 0:
        chosen = [p for p in candidates if p.age_days(now) > settings.max_days]
    if settings.max_gib > 0:
        total = sum(p.bytes for p in infos) - sum(p.bytes for p in chosen)
        limit = settings.max_gib * GIB
        for info in candidates:
            if total <= limit:
                break
            if info not in chosen:
                chosen.append(info)
                total -= info.bytes
    return chosen


_prune_lock = threading.Lock()


def prune(server: Host, why: str, dry_run: bool = False) -> PruneReport:
    """Apply the rule now; log what was (or would be) removed."""
    settings: StorageSettings = server.settings.storage
    with _prune_lock:
        infos = list_products(server.products.root)
        protected = protected_products(server, infos)
        chosen = choose(settings, infos, protected)
        removed = []
        for info in chosen:
            if not dry_run:
                try:
                    _remove(info.path)
                except OSError as exc:
                    log.warning("retention (%s): cannot remove %s: %s", why, info.path, exc)
                    continue
            removed.append(info)
        total = sum(p.bytes for p in infos)
        report = PruneReport(removed, total - sum(p.bytes for p in removed), total, protected, dry_run)
    if removed:
        verb = "would remove" if dry_run else "removed"
        log.info("retention (%s): %s %d product(s), %.1f MiB: %s", why, verb, len(removed),
                 report.freed_bytes / 2**20, ", ".join(p.name for p in removed))
    if not dry_run:
        files.storage_changed(server.products.root)
    return report


def _remove(path: Path) -> None:
    """Remove a product folder: renamed to a hidden name first, so nobody sees half of it go."""
    hidden = path.with_name(f".removing-{path.name}-{os.getpid()}")
    os.rename(path, hidden)
    shutil.rmtree(hidden)


# ------------------------------------------------------------------------------------------------
# Free space and the storage error


def free_space(path: Path, cap_root: Path | None = None, cap_bytes: int = 0) -> int:
    """Bytes still writable at `path`: the disk's free space, or less under the cap."""
    probe = Path(path)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:
        free = 0
    if cap_root is not None and cap_bytes > 0:
        free = min(free, max(0, cap_bytes - files.tree_bytes(cap_root)))
    return free


def enospc_of(exc: BaseException | None) -> OSError | None:
    """The ENOSPC OSError in `exc` or what caused it, if any."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def human_bytes(count: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(count) < 1024 or unit == "GiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} GiB"
