"""View planning: the pan-tilt positions that let a camera see a range of directions.

The thesis' GetPtuPositions: given the pan and tilt ranges to cover (the directions to see, radians,
in the PTU's angles: pan positive right, tilt positive up), the camera's horizontal and vertical field
of view and the overlap wanted between neighbouring views, return the (pan, tilt) positions, ordered
so the PTU travels little.

How:
1. Tilt rows: the tilt range is cut into equal bands no taller than vfov * (1 - overlap); one row of
   views looks at the middle of each band, so every band lies inside the frame with a margin.
2. Pan step per row: a tilted pinhole camera does not see a constant width of azimuth: seen from the
   pan axis its frame is a keystone, narrowest at the band edge farther from the horizon. The row's
   step is (1 - overlap) times the azimuth width the frame covers at EVERY elevation of its band, so
   coverage holds at the corners, not only on the centre line.
3. Pan positions: evenly spread over the range; a full circle gets n views 2*pi/n apart and no
   duplicated seam view.
4. Serpentine order: rows bottom-up, pan alternately increasing and decreasing, so the PTU never
   swings back across the whole range (and never across a full circle's seam).

The camera is taken to sit on the pan and tilt axes, looking along head x: the few centimetres and
tenths of a degree of a real mount are far inside the overlap margin.
"""
from __future__ import annotations

import math

import numpy as np

from toolbox.geometry import direction_of

FULL_CIRCLE = 2 * math.pi
ANGLE_TOLERANCE = 1e-9
BISECTION_STEPS = 60
BAND_SAMPLES = 9


def plan_views(pan_range: tuple[float, float], tilt_range: tuple[float, float], horizontal_fov: float,
               vertical_fov: float, overlap: float = 0.1) -> np.ndarray:
    """(N, 2) array of (pan, tilt) radians covering the ranges, in serpentine order.

    A pan range spanning 2*pi or more is a full panorama. Raises ValueError on an empty range, a
    field of view outside (0, pi), or an overlap outside [0, 1)."""
    _check(pan_range, tilt_range, horizontal_fov, vertical_fov, overlap)
    rows = []
    for tilt, band in tilt_rows(tilt_range, vertical_fov, overlap):
        half_width = covered_half_width(tilt, band, horizontal_fov, vertical_fov)
        pans = pan_positions(pan_range, half_width, overlap)
        rows.append(np.column_stack([pans, np.full(len(pans), tilt)]))
    return serpentine(rows)


def tilt_rows(tilt_range: tuple[float, float], vertical_fov: float, overlap: float) -> list[tuple[float, tuple]]:
    """Centre tilt of each row and the band of elevations (low, high) it is responsible for."""
    low, high = tilt_range
    band_height = vertical_fov * (1 - overlap)
    count = max(1, math.ceil((high - low) / band_height - ANGLE_TOLERANCE))
    step = (high - low) / count
    return [(low + (i + 0.5) * step, (low + i * step, low + (i + 1) * step)) for i in range(count)]


def covered_half_width(tilt: float, band: tuple[float, float], horizontal_fov: float, vertical_fov: float) -> float:
    """Half the azimuth width a camera at (pan 0, tilt) sees at every elevation within `band`."""
    elevations = np.linspace(band[0], band[1], BAND_SAMPLES)
    inside_low = np.zeros_like(elevations)          # azimuths known to be inside
    outside_high = np.full_like(elevations, math.pi)
    if not in_view(0.0, tilt, horizontal_fov, vertical_fov, np.zeros_like(elevations), elevations).all():
        raise ValueError(f"the tilt band {np.degrees(band)} deg does not fit in the vertical field of view")
    for _ in range(BISECTION_STEPS):
        middle = (inside_low + outside_high) / 2
        seen = in_view(0.0, tilt, horizontal_fov, vertical_fov, middle, elevations)
        inside_low = np.where(seen, middle, inside_low)
        outside_high = np.where(seen, outside_high, middle)
    half_width = float(inside_low.min())
    if half_width < 0.01 * horizontal_fov:   # hundreds of views per row: the frames barely meet
        raise ValueError("the views' frames only touch at the corners: ask for some overlap (> 0)")
    return half_width


def pan_positions(pan_range: tuple[float, float], half_width: float, overlap: float) -> np.ndarray:
    """Pan angles of one row whose views each reliably cover +-half_width around their centre."""
    low, high = pan_range
    step = 2 * half_width * (1 - overlap)
    if high - low >= FULL_CIRCLE - ANGLE_TOLERANCE:
        count = max(1, math.ceil(FULL_CIRCLE / step - ANGLE_TOLERANCE))
        return low + (np.arange(count) + 0.5) * (FULL_CIRCLE / count)
    if high - low <= 2 * half_width:
        return np.array([(low + high) / 2])
    count = math.ceil((high - low - 2 * half_width) / step - ANGLE_TOLERANCE) + 1
    return np.linspace(low + half_width, high - half_width, count)


def serpentine(rows: list[np.ndarray]) -> np.ndarray:
    """Rows bottom-up; odd rows reversed so each row starts where the previous one ended."""
    ordered = [row if i % 2 == 0 else row[::-1] for i, row in enumerate(rows)]
    return np.concatenate(ordered, axis=0)


def in_view(view_pan: float, view_tilt: float, horizontal_fov: float, vertical_fov: float,
            pan: float | np.ndarray, tilt: float | np.ndarray) -> np.ndarray:
    """True where the direction at PTU angles (pan, tilt) falls inside the frame of a camera
    looking from the PTU centre at (view_pan, view_tilt) (pinhole, square frame edges)."""
    direction = direction_of(pan, tilt)
    forward = direction_of(view_pan, view_tilt)
    right = np.array([-math.sin(view_pan), -math.cos(view_pan), 0.0])   # camera x, horizontal
    down = np.cross(forward, right)                                      # camera y
    z = direction @ forward
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = (direction @ right) / z, (direction @ down) / z
    return (z > 0) & (np.abs(x) <= math.tan(horizontal_fov / 2) + 1e-12) & \
        (np.abs(y) <= math.tan(vertical_fov / 2) + 1e-12)


def travel(views: np.ndarray) -> float:
    """PTU travel through the views in order: the sum of max(|d pan|, |d tilt|) (both axes move at once)."""
    steps = np.abs(np.diff(np.asarray(views), axis=0))
    return float(steps.max(axis=1).sum()) if len(steps) else 0.0


def _check(pan_range: tuple[float, float], tilt_range: tuple[float, float], horizontal_fov: float,
           vertical_fov: float, overlap: float) -> None:
    for name, (low, high) in (("pan range", pan_range), ("tilt range", tilt_range)):
        if not high >= low:
            raise ValueError(f"{name} must be (low, high) with low <= high, got {(low, high)}")
    if not -math.pi / 2 <= tilt_range[0] <= tilt_range[1] <= math.pi / 2:
        raise ValueError("tilt range must lie within +-90 degrees")
    for name, fov in (("horizontal", horizontal_fov), ("vertical", vertical_fov)):
        if not 0 < fov < math.pi:
            raise ValueError(f"{name} field of view must be in (0, 180) degrees, got {math.degrees(fov):g}")
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap!r}")
