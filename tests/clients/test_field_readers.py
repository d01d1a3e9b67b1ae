"""Products opened by the field's own readers, not ours (issue 48, item 3).

One small dem-full-tof run on a real server over the simulated world, then every file of the product
through the library a user of the product would reach for: each GeoTIFF through rasterio (GDAL), its
geotransform, frame and no-data value against what product.json's `grids` says; the PLY cloud through
Open3D's reader and through plyfile, its point count and bounds against product.json's `clouds`; every
PNG through Pillow. Our own readers (rvs_server.products) are only used to say what the pixels are.
"""
from __future__ import annotations

import json
import logging
import math

import numpy as np
import open3d as o3d
import plyfile  # the readers come with the test extra (pyproject.toml), so a missing one fails, not skips
import pytest
import rasterio
from PIL import Image as PIL_Image

from rvs_server.products.ply import read_ply
from rvs_server.products.rasters import read_geotiff, read_png

from conftest import one_product


@pytest.fixture(scope="module")
def product(tmp_path_factory):
    """A quarter-panorama DEM from the TOF camera: GeoTIFFs (maps and truth), a PLY cloud, PNG pictures."""
    server, reply = one_product(tmp_path_factory.mktemp("readers"), "dem-full-tof --pan -30:30 --output readers")
    path = server.data_dir / "products" / reply["product"]
    manifest = json.loads((path / "product.json").read_text())
    assert manifest["status"] == "complete"
    return path, manifest


def _files(manifest, *suffixes):
    return sorted(name for name in manifest["files"] if name.endswith(suffixes))


def test_every_geotiff_opens_in_gdal_where_product_json_puts_it(product, caplog):
    path, manifest = product
    tifs = _files(manifest, ".tif")
    assert "dem.tif" in tifs and "truth/height.tif" in tifs
    assert sorted(manifest["grids"]) == tifs  # every GeoTIFF is placed by the manifest
    caplog.set_level(logging.WARNING)  # GDAL's warnings (a bad tag, a guessed no-data) reach Python's logging
    for name in tifs:
        grid = manifest["grids"][name]
        (x0, y0), cell, rows, cols = grid["origin"], grid["cell"], grid["rows"], grid["cols"]
        with rasterio.open(path / name) as ds:
            assert ds.driver == "GTiff" and ds.count == 1 and ds.dtypes == ("float32",), name
            assert (ds.height, ds.width) == (rows, cols), name
            # North up: the top-left corner is the origin's x and the north edge; rows go south.
            expected = rasterio.Affine(cell, 0.0, x0, 0.0, -cell, y0 + rows * cell)
            assert ds.transform.almost_equals(expected, precision=1e-9), (name, ds.transform, expected)
            assert ds.tags().get("AREA_OR_POINT") == "Area", name  # the transform is of cell corners
            assert ds.bounds.left == pytest.approx(x0) and ds.bounds.bottom == pytest.approx(y0)
            assert ds.nodata is not None and math.isnan(ds.nodata), (name, ds.nodata)
            # frame "world": a local engineering frame in metres, east and north (not a geodetic CRS)
            assert grid["frame"] == "world"
            wkt = ds.crs.to_wkt()
            assert wkt.startswith("LOCAL_CS[") and "RVS world frame" in wkt, wkt
            assert 'AXIS["Easting",EAST]' in wkt and 'AXIS["Northing",NORTH]' in wkt, wkt
            assert ds.crs.units_factor == ("metre", 1.0)
            values = ds.read(1)
            masked = ds.read(1, masked=True)
        ours, _ = read_geotiff(path / name)
        # GDAL's pixels are ours, north up; its no-data mask is exactly our NaN cells.
        np.testing.assert_array_equal(values, np.flipud(ours), err_msg=name)
        np.testing.assert_array_equal(masked.mask, np.isnan(values), err_msg=name)
    gdal_warnings = [r.getMessage() for r in caplog.records if r.name.startswith("rasterio")]
    assert not gdal_warnings, gdal_warnings


def test_gdal_finds_a_world_point_in_the_cell_the_manifest_says(product):
    """The orientation check: a known cell's centre, given to GDAL as world x, y, lands on that cell."""
    path, manifest = product
    grid = manifest["grids"]["dem.tif"]
    (x0, y0), cell = grid["origin"], grid["cell"]
    dem, _ = read_geotiff(path / "dem.tif")  # rows northwards
    known = np.argwhere(np.isfinite(dem))
    picks = known[np.linspace(0, len(known) - 1, 25).astype(int)]
    with rasterio.open(path / "dem.tif") as ds:
        band = ds.read(1)
        xs = [x0 + (c + 0.5) * cell for _, c in picks]
        ys = [y0 + (r + 0.5) * cell for r, _ in picks]
        sampled = [v[0] for v in ds.sample(zip(xs, ys, strict=True))]
        for (r, c), x, y, value in zip(picks, xs, ys, sampled, strict=True):
            row, col = ds.index(x, y)
            assert (row, col) == (grid["rows"] - 1 - r, c)
            assert band[row, col] == dem[r, c] == value


def test_ply_clouds_open_in_open3d_and_plyfile_with_the_manifests_count_and_bounds(product):
    path, manifest = product
    plys = _files(manifest, ".ply")
    assert plys == ["cloud.ply"] and sorted(manifest["clouds"]) == plys
    for name in plys:
        said = manifest["clouds"][name]
        assert said["points"] > 1000 and said["frame"] == "world"
        cloud = o3d.io.read_point_cloud(str(path / name), format="ply", print_progress=False)
        points = np.asarray(cloud.points)
        assert len(points) == said["points"], name
        np.testing.assert_allclose(cloud.get_min_bound(), said["min"], atol=1e-6)
        np.testing.assert_allclose(cloud.get_max_bound(), said["max"], atol=1e-6)
        data = plyfile.PlyData.read(str(path / name))
        assert [e.name for e in data.elements] == ["vertex"] and data.text is False
        assert data.byte_order == "<"
        vertex = data["vertex"]
        assert vertex.count == said["points"]
        xyz = np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)
        np.testing.assert_allclose(xyz.min(axis=0), said["min"], atol=1e-6)
        np.testing.assert_allclose(xyz.max(axis=0), said["max"], atol=1e-6)
        assert any("world frame" in comment for comment in data.comments)
        np.testing.assert_array_equal(xyz, points)  # both readers see the same points, in order
        ours = read_ply(path / name)
        np.testing.assert_array_equal(xyz[:, 2], ours["z"])


def test_every_png_opens_in_pillow_with_our_pixels(product):
    path, manifest = product
    pngs = _files(manifest, ".png")
    assert {"dem.png", "hazard.png", "overview.png"} <= set(pngs)
    for name in pngs:
        with PIL_Image.open(path / name) as image:
            assert image.format == "PNG", name
            image.verify()  # checks the chunks and their CRCs
        with PIL_Image.open(path / name) as image:
            image.load()
            assert image.mode in ("RGB", "L", "RGBA"), (name, image.mode)
            pixels = np.asarray(image)
        np.testing.assert_array_equal(pixels, read_png(path / name), err_msg=name)
