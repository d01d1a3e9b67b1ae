"""Writing and reading the files products hold: TIFF of raw values, GeoTIFF grids, PNG pictures.

GeoTIFFs are float32 with NaN as no-data and carry the grid's georeferencing in the standard tags
(ModelPixelScale, ModelTiepoint, GeoKeyDirectory, GDAL_NODATA), so GDAL and rasterio open them with
their origin and cell size. The world frame is a local engineering frame, declared as a
user-defined projected system in metres. Grids are stored north up (the array flipped on its first
axis, since RVS grids count rows northwards). Every file is written atomically (rvs_server.files).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile

from rvs_server.files import atomic_file, atomic_path
from toolbox.grid import GridSpec

# GeoTIFF keys: raster is "pixel is area"; model type projected; a user-defined projection in metres.
_GT_MODEL_TYPE, _GT_RASTER_TYPE, _PROJECTED_CS, _PROJ_LINEAR_UNITS, _GT_CITATION = 1024, 1025, 3072, 3076, 1026
_USER_DEFINED, _METRE = 32767, 9001


def write_png(path: Path, rgb: np.ndarray) -> Path:
    """RGB (or grey) uint8 to PNG."""
    image = rgb[..., ::-1] if rgb.ndim == 3 else rgb
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise ValueError(f"cannot encode {path} as PNG")
    with atomic_file(path) as handle:  # written by Python, so a full disk is an OSError with its errno
        handle.write(encoded.tobytes())
    return path


def read_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise OSError(f"cannot read {path}")
    return image[..., ::-1] if image.ndim == 3 else image


def write_tiff(path: Path, array: np.ndarray, description: str = "", metadata: dict[str, Any] | None = None) -> Path:
    """Raw values, unchanged dtype, with a description and JSON metadata in the file."""
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, array, description=description or None, metadata=metadata or None,
                         compression="zlib", photometric="minisblack" if array.ndim == 2 else None)
    return path


def read_tiff(path: Path) -> np.ndarray:
    return tifffile.imread(path)


def write_geotiff(path: Path, grid_values: np.ndarray, grid: GridSpec, description: str = "") -> Path:
    """A float32 grid as a GeoTIFF, north up, NaN no-data, origin and cell size in the tags."""
    if grid_values.shape[:2] != grid.shape:
        raise ValueError(f"values of shape {grid_values.shape} do not fit grid {grid.shape}")
    north_up = np.ascontiguousarray(np.flipud(grid_values.astype(np.float32)))
    top = grid.origin_y + grid.rows * grid.cell
    citation = "RVS world frame: x east, y north, metres (local, not geodetic)"
    geokeys = [1, 1, 0, 5,
               _GT_MODEL_TYPE, 0, 1, 1,          # projected
               _GT_RASTER_TYPE, 0, 1, 1,         # pixel is area
               _GT_CITATION, 34737, len(citation) + 1, 0,
               _PROJECTED_CS, 0, 1, _USER_DEFINED,
               _PROJ_LINEAR_UNITS, 0, 1, _METRE]
    extratags = [
        (33550, "d", 3, (grid.cell, grid.cell, 0.0), True),               # ModelPixelScaleTag
        (33922, "d", 6, (0.0, 0.0, 0.0, grid.origin_x, top, 0.0), True),  # ModelTiepointTag
        (34735, "H", len(geokeys), geokeys, True),                        # GeoKeyDirectoryTag
        (34737, "s", 0, citation + "|", True),                            # GeoAsciiParamsTag
        (42113, "s", 0, "nan", True),                                     # GDAL_NODATA
    ]
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, north_up, description=description or None, extratags=extratags,
                         compression="zlib", photometric="minisblack", metadata=None)
    return path


def geotiff_grid(path: Path) -> GridSpec | None:
    """The grid of a GeoTIFF written by write_geotiff, from its tags alone (no pixels read); None for a
    TIFF without them."""
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert isinstance(page, tifffile.TiffPage)   # the first page is never a TiffFrame
        if 33550 not in page.tags or 33922 not in page.tags:
            return None
        scale, tie = page.tags[33550].value, page.tags[33922].value
        rows, cols = page.shape[:2]
    cell = float(scale[0])
    return GridSpec(float(tie[3]), float(tie[4]) - rows * cell, cell, int(rows), int(cols))


def read_geotiff(path: Path) -> tuple[np.ndarray, GridSpec]:
    """Inverse of write_geotiff: the grid values (rows northwards) and their GridSpec."""
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert isinstance(page, tifffile.TiffPage)   # the first page is never a TiffFrame
        values = page.asarray()
        scale = page.tags[33550].value
        tie = page.tags[33922].value
    rows, cols = values.shape[:2]
    cell = float(scale[0])
    grid = GridSpec(float(tie[3]), float(tie[4]) - rows * cell, cell, rows, cols)
    return np.flipud(values), grid
