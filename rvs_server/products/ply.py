"""Point clouds as binary little-endian PLY, the one writer every product uses: float x, y, z (world
frame, metres), optional uchar red, green, blue and ushort `hop`; Open3D, CloudCompare and MeshLab read
them (and ignore `hop`). Written atomically (rvs_server.files)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rvs_server.files import atomic_file

_PLY_TYPES = {"float": "<f4", "uchar": "u1", "ushort": "<u2", "int": "<i4", "double": "<f8"}


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray | None = None,
              hops: np.ndarray | None = None) -> Path:
    """Binary PLY: float x, y, z (world frame, metres), optional uchar red, green, blue and a ushort
    `hop` index; Open3D, CloudCompare and MeshLab read it (and ignore `hop`)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if hops is not None:
        fields += [("hop", "<u2")]
    vertices = np.empty(len(points), dtype=fields)
    for axis, name in enumerate("xyz"):
        vertices[name] = points[:, axis]
    if colours is not None:
        colours = np.asarray(colours).reshape(-1, 3)
        for channel, name in enumerate(("red", "green", "blue")):
            vertices[name] = colours[:, channel]
    if hops is not None:
        vertices["hop"] = hops
    names = {np.dtype(v): k for k, v in _PLY_TYPES.items()}
    properties = "".join(f"property {names[np.dtype(t)]} {n}\n" for n, t in fields)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment RVS world frame (x east, y north, z up), metres\n"
              f"element vertex {len(points)}\n{properties}end_header\n")
    with atomic_file(path) as handle:
        handle.write(header.encode("ascii"))
        handle.write(vertices.tobytes())
    return path


def read_ply(path: Path) -> np.ndarray:
    """The vertices of a binary little-endian PLY written by write_ply, as a structured array."""
    with open(path, "rb") as handle:
        data = handle.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    count, fields = 0, []
    for line in data[:end].decode("ascii").splitlines():
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[:1] == ["property"]:
            fields.append((words[2], _PLY_TYPES[words[1]]))
    return np.frombuffer(data, dtype=fields, count=count, offset=end)


def ply_summary(path: Path) -> dict | None:
    """What a PLY written by write_ply holds, for the product's manifest: the vertex count and the
    bounds of x, y, z (metres, world frame); None for a file that is not such a PLY."""
    vertices = read_ply(path)
    if not {"x", "y", "z"} <= set(vertices.dtype.names or ()):
        return None
    xyz = np.stack([vertices[name] for name in "xyz"], axis=1)
    if len(xyz) == 0:
        return {"points": 0, "min": None, "max": None, "frame": "world"}
    return {"points": int(len(xyz)), "min": [round(float(v), 6) for v in xyz.min(axis=0)],
            "max": [round(float(v), 6) for v in xyz.max(axis=0)], "frame": "world"}
