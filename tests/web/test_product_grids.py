"""product.json says where each GeoTIFF lies in the world, so the page can place maps and paths."""
from __future__ import annotations

import json

import numpy as np

from rvs_server.products.manifests import Products
from rvs_server.products.rasters import write_geotiff, write_png
from toolbox.grid import GridSpec


def test_finish_records_every_geotiffs_grid(tmp_path):
    product = Products(tmp_path).create("dem-full", "grids", {})
    spec = GridSpec(-3.0, 1.5, 0.05, 40, 60)
    write_geotiff(product.add("dem.tif", "height"), np.zeros(spec.shape, np.float32), spec)
    write_geotiff(product.add("truth/height.tif", "true height"), np.ones(spec.shape, np.float32), spec)
    write_png(product.add("dem.png", "picture"), np.zeros((8, 8, 3), np.uint8))
    product.add("missing.tif", "never written")
    manifest = json.loads(product.finish().read_text())
    assert manifest["grids"] == {
        name: {"origin": [-3.0, 1.5], "cell": 0.05, "rows": 40, "cols": 60, "frame": "world"}
        for name in ("dem.tif", "truth/height.tif")}


def test_a_product_without_grids_has_no_grids_key(tmp_path):
    product = Products(tmp_path).create("grab-tof", "plain", {})
    product.write_json("frame.json", {"a": 1}, "a frame")
    assert "grids" not in json.loads(product.finish().read_text())
