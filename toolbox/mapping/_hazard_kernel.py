"""The compiled plane fit of hazard.plane_fit (numba), imported only for large grids.

numpy and OpenCV need ten float64 box filters and some forty whole-grid array operations for the
fit; on a 1000 x 1000 grid the array operations alone took several times the box filters (memory
traffic, not arithmetic). Here one pass does it all with running window sums: moving down the
rows, six column sums of the window's rows are kept up to date (mask, mask y, mask y^2, z, z^2,
z y; a row enters, a row leaves), and along each row ten running sums of them over the window's
columns give the normal equations (mask 1, x, y, x^2, y^2, xy; z 1, z^2, zx, zy) of each cell,
solved on the spot. x and y are in cells from the grid's middle; the mask's sums are integers and
exact, the heights' within a few ulps of the direct sums. Strips of rows run on numba's threads.
"""
from __future__ import annotations

import math

import numba
import numpy as np

# numba tries TBB first and warns where the installed TBB is too old; OpenMP is as fast here and,
# unlike the workqueue layer, safe when several Python threads fit planes at once.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


# Rows per strip: the strips run in parallel (numba threads); each starts from its own window sums,
# so the result does not depend on the number of threads.
STRIP_ROWS = 128


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _add_row(z: np.ndarray, known: np.ndarray, centre: float, row: int, y: float, sign: float, v0: np.ndarray,
             v1: np.ndarray, v2: np.ndarray, v3: np.ndarray, v4: np.ndarray, v5: np.ndarray) -> None:
    for c in range(z.shape[1]):
        w = sign if known[row, c] else 0.0
        zc = (z[row, c] - centre) if known[row, c] else 0.0
        v0[c] += w
        v1[c] += w * y
        v2[c] += w * y * y
        v3[c] += w * zc
        v4[c] += w * zc * zc
        v5[c] += w * zc * y


@numba.njit(cache=True, nogil=True, boundscheck=False, parallel=True)
def plane_fit_cells(z: np.ndarray, known: np.ndarray, centre: float, k: int, min_cells: int, tangent: np.ndarray,
                    roughness: np.ndarray) -> None:
    """Per cell, the plane's gradient magnitude (metres per cell) into `tangent` and its roughness
    (metres) into `roughness`, NaN where the cell is unknown, has fewer than min_cells known cells
    in its window or they lie on a line. Heights are taken relative to `centre` (for precision)."""
    rows = z.shape[0]
    strips = (rows + STRIP_ROWS - 1) // STRIP_ROWS
    for strip in numba.prange(strips):
        top = strip * STRIP_ROWS
        _plane_fit_strip(z, known, centre, k, min_cells, tangent, roughness, top, min(rows, top + STRIP_ROWS))


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _plane_fit_strip(z: np.ndarray, known: np.ndarray, centre: float, k: int, min_cells: int, tangent: np.ndarray,
                     roughness: np.ndarray, top: int, bottom: int) -> None:
    rows, cols = z.shape
    ox, oy = cols // 2, rows // 2
    v0, v1, v2 = np.zeros(cols), np.zeros(cols), np.zeros(cols)
    v3, v4, v5 = np.zeros(cols), np.zeros(cols), np.zeros(cols)
    # The column sums of the window of row top - 1, then down the strip: row r + k enters the
    # window of row r, row r - k - 1 leaves it.
    for row in range(max(0, top - 1 - k), min(rows, top + k)):
        _add_row(z, known, centre, row, float(row - oy), 1.0, v0, v1, v2, v3, v4, v5)
    for r in range(top, bottom):
        if r + k < rows:
            _add_row(z, known, centre, r + k, float(r + k - oy), 1.0, v0, v1, v2, v3, v4, v5)
        if r - k - 1 >= 0:
            _add_row(z, known, centre, r - k - 1, float(r - k - 1 - oy), -1.0, v0, v1, v2, v3, v4, v5)
        n = sx = sy = sxx = syy = sxy = sz = szz = sxz = syz = 0.0
        for c in range(-k, cols):
            # Along the row: column c + k enters the window of column c, c - k - 1 leaves it.
            e = c + k
            if e < cols:
                x = float(e - ox)
                n += v0[e]
                sx += v0[e] * x
                sy += v1[e]
                sxx += v0[e] * x * x
                syy += v2[e]
                sxy += v1[e] * x
                sz += v3[e]
                szz += v4[e]
                sxz += v3[e] * x
                syz += v5[e]
            e = c - k - 1
            if e >= 0:
                x = float(e - ox)
                n -= v0[e]
                sx -= v0[e] * x
                sy -= v1[e]
                sxx -= v0[e] * x * x
                syy -= v2[e]
                sxy -= v1[e] * x
                sz -= v3[e]
                szz -= v4[e]
                sxz -= v3[e] * x
                syz -= v5[e]
            if c < 0:
                continue
            tangent[r, c] = np.nan
            roughness[r, c] = np.nan
            if not known[r, c] or n < min_cells - 0.5:
                continue
            mx, my, mz = sx / n, sy / n, sz / n
            cxx, cyy, cxy = sxx - sx * mx, syy - sy * my, sxy - sx * my
            cxz, cyz, czz = sxz - mx * sz, syz - my * sz, szz - sz * mz
            det = cxx * cyy - cxy * cxy
            if not det > 1e-12 * n * n:
                continue
            inverse = 1.0 / det
            a = (cyy * cxz - cxy * cyz) * inverse
            b = (cxx * cyz - cxy * cxz) * inverse
            tangent[r, c] = math.sqrt(a * a + b * b)
            roughness[r, c] = math.sqrt(max(czz - a * cxz - b * cyz, 0.0) / (n - 3))
