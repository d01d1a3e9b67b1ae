"""Writing the data directory's files so that a kill or a power cut at any moment leaves the old
file or the new one, never half of one.

Every write goes to a temporary file beside its target, hidden and named `.NAME.tmp-PID-N`
(`.STEM.tmp-PID-N.EXT` where a library picks the format by the extension), is flushed and fsynced,
then renamed onto the final name with os.replace (atomic on POSIX), and the directory is fsynced so
the rename itself survives a power cut. A write that raises removes its temporary file; one cut
short by a kill cannot, so `remove_stale_temporaries` clears them when the server starts. Nothing
the server makes starts with a dot, so a temporary file is never taken for a product or a
checkpoint meanwhile.
"""
from __future__ import annotations

import contextlib
import errno
import itertools
import json
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np

log = logging.getLogger("rvs.files")

_serial = itertools.count(1)  # two threads writing the same name never share a temporary file
# Ours: `.NAME.tmp-PID-N[.EXT]`; and the bare `.NAME.tmp[.EXT]` earlier versions left.
TEMPORARY = re.compile(r"^\..+\.tmp(?:-(?P<pid>\d+)-\d+)?(?:\.[A-Za-z0-9]+)?$")


def temporary_name(path: Path, keep_suffix: bool = False) -> Path:
    """The hidden temporary file for `path`, in the same directory (os.replace cannot cross file
    systems); with `keep_suffix` it ends in the target's extension."""
    tag = f"tmp-{os.getpid()}-{next(_serial)}"
    if keep_suffix and path.suffix:
        return path.with_name(f".{path.stem}.{tag}{path.suffix}")
    return path.with_name(f".{path.name}.{tag}")


def is_temporary(name: str) -> bool:
    return TEMPORARY.match(name) is not None


@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "wb", **open_args: Any) -> Iterator[IO]:
    """An open file that becomes `path` when the block ends without an exception."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_file writes a new file (mode w or wb), not mode {mode!r}")
    path = Path(path)
    tmp = temporary_name(path)
    try:
        with open(tmp, mode, **open_args) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        _check_cap(tmp, path)
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        _name_the_file(exc, path)
        raise
    _fsync_directory(path.parent)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path with `path`'s extension, for libraries that want a file name (cv2.imwrite
    picks its encoder by it); whatever was written there becomes `path` when the block ends."""
    path = Path(path)
    tmp = temporary_name(path, keep_suffix=True)
    try:
        yield tmp
        _fsync_file(tmp)
        _check_cap(tmp, path)
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        _name_the_file(exc, path)
        raise
    _fsync_directory(path.parent)


def write_text_atomic(path: str | Path, text: str) -> Path:
    with atomic_file(path, "w", encoding="utf-8") as handle:
        handle.write(text)
    return Path(path)


def write_json_atomic(path: str | Path, data: Any, default: Callable[[Any], Any] | None = None) -> Path:
    return write_text_atomic(path, json.dumps(data, indent=1, default=default) + "\n")


def save_npy_atomic(path: str | Path, array: np.ndarray) -> Path:
    with atomic_file(path, "wb") as handle:  # a file object: np.save adds no extension
        np.save(handle, np.asarray(array), allow_pickle=False)
    return Path(path)


def save_npz_atomic(path: str | Path, arrays: Mapping[str, Any], compressed: bool = False) -> Path:
    save = np.savez_compressed if compressed else np.savez
    with atomic_file(path, "wb") as handle:
        save(handle, **arrays)
    return Path(path)


def remove_stale_temporaries(root: str | Path) -> list[Path]:
    """Delete the temporary files that writes cut short by a kill left under `root` (any but this
    process's own), and log what went. Run at start-up, before any job writes."""
    root = Path(root)
    own = str(os.getpid())
    removed = []
    for folder, _, names in os.walk(root):
        for name in names:
            match = TEMPORARY.match(name)
            if match is None or match.group("pid") == own:
                continue
            path = Path(folder) / name
            try:
                path.unlink()
            except FileNotFoundError:
                continue
            removed.append(path)
    if removed:
        shown = ", ".join(str(p.relative_to(root)) for p in removed[:5])
        more = f" and {len(removed) - 5} more" if len(removed) > 5 else ""
        log.warning("removed %d temporary file(s) that interrupted writes left in %s: %s%s",
                    len(removed), root, shown, more)
    return removed


# ------------------------------------------------------------------------------------------------
# The storage cap (server.toml [storage] cap_gib): a folder whose files may take at most so many
# bytes. A write that would pass it fails with ENOSPC before its rename, as on a full disk, and its
# temporary file is removed, so the same path (the job runner's ERR 507) serves both.

_caps: dict[Path, int] = {}
_usage: dict[Path, tuple[float, int]] = {}  # root -> (when measured, bytes then + bytes written since)
_caps_lock = threading.Lock()
_USAGE_FRESH_S = 5.0


def set_storage_cap(root: str | Path, cap_bytes: int) -> None:
    """Cap what the files under `root` may take (0 removes the cap)."""
    root = Path(root).absolute()
    with _caps_lock:
        if cap_bytes > 0:
            _caps[root] = int(cap_bytes)
        else:
            _caps.pop(root, None)
        _usage.pop(root, None)


def storage_cap(root: str | Path) -> int:
    return _caps.get(Path(root).absolute(), 0)


def storage_changed(root: str | Path) -> None:
    """Files under `root` were removed (or added outside these functions): measure again."""
    with _caps_lock:
        _usage.pop(Path(root).absolute(), None)


def tree_bytes(root: str | Path) -> int:
    total = 0
    for folder, _, names in os.walk(root):
        for name in names:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except FileNotFoundError:
                pass
    return total


def _check_cap(tmp: Path, path: Path) -> None:
    if not _caps:
        return
    target = path.absolute()
    for root, cap in list(_caps.items()):
        if not target.is_relative_to(root):
            continue
        size = tmp.stat().st_size
        with _caps_lock:
            when, used = _usage.get(root, (0.0, -1))
            if used < 0 or time.monotonic() - when > _USAGE_FRESH_S:
                when, used = time.monotonic(), tree_bytes(root) - size  # the temporary file is counted apart
            if used + size > cap:
                _usage.pop(root, None)  # measured afresh next time: space is often freed by hand
                raise OSError(errno.ENOSPC, f"No space left on device (the storage cap of {cap} bytes on "
                                            f"{root} is reached: {used} used, {size} more asked)", str(path))
            _usage[root] = (when, used + size)


def _name_the_file(exc: BaseException, path: Path) -> None:
    """A write that fails in a file object (a full disk) names no file: name the one being written."""
    if isinstance(exc, OSError) and exc.filename is None:
        exc.filename = str(path)


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_directory(directory: Path) -> None:
    """Make a rename in `directory` durable; a file system that cannot fsync a directory is left be."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
