"""dem-full-fused on a real server: the SR4000's and the stereo pair's DEMs of the same views as one."""
from __future__ import annotations

import json

import numpy as np

from rvs_server.products.rasters import read_geotiff

from conftest import REPO, pairs


def near_rover(product, within_m: float = 4.0):
    """(the DEM's measured cells within `within_m` of the rover at the origin, their error against the truth)"""
    dem, spec = read_geotiff(product / "dem.tif")
    counts, _ = read_geotiff(product / "counts.tif")
    truth, _ = read_geotiff(product / "truth" / "height.tif")
    xs, ys = spec.centres()
    measured = np.isfinite(dem) & (counts > 0) & (np.hypot(xs[None, :], ys[:, None]) <= within_m)
    return measured, (dem - truth)[measured]


def test_the_fused_map_covers_more_than_the_tof_at_its_precision(server):
    with server.connect() as c:
        fused = pairs(c.command("dem-full-fused --pan -60:60 --output fused", timeout=600))
        assert " OK " in c.command("dem-full-tof --pan -60:60 --output tof", timeout=600)
    root = server.data_dir / "products"
    note = json.loads((root / "fused" / "product.json").read_text())["fusion"]
    assert note["bias_measured"] and float(fused["stereo_bias"]) == note["stereo_bias_m"]
    assert int(fused["shared_cells"]) == note["shared_cells"] > 1000
    assert {"views_plan", "acquire_tof", "acquire_stereo"} <= {p.stem for p in (root / "fused" / "views").glob("*.npz")}
    fused_cells, fused_error = near_rover(root / "fused")
    tof_cells, tof_error = near_rover(root / "tof")
    rmse = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert fused_cells.sum() > 1.1 * tof_cells.sum()            # the stereo fills what the TOF missed
    assert rmse(fused_error) < 0.015 and rmse(fused_error) < rmse(tof_error) + 0.003
    assert abs(float(np.median(fused_error))) < 0.005


def test_a_fused_map_remapped_with_its_workflow_is_the_same_map_with_its_fusion_noted(server, capfd):
    """rvs remap on a dem-full-fused product: both sensors' stored views, the same DEM and the same
    fusion findings in product.json (the remapped product once lacked them)."""
    from clients.cli import main as rvs
    with server.connect() as c:
        reply = pairs(c.command("dem-full-fused --pan -30:30 --output narrow", timeout=600))
    source = server.data_dir / "products" / "narrow"
    assert rvs(["remap", str(source), "--workflow", str(REPO / "workflows" / "dem-full-fused.yaml"),
                "--workers", "1"]) == 0
    assert capfd.readouterr().out.strip().splitlines()[-1].startswith("narrow -> narrow-remap known ")
    remapped = source.parent / "narrow-remap"
    before, after = (json.loads((p / "product.json").read_text())["fusion"] for p in (source, remapped))
    assert before == after and before["stereo_bias_m"] == float(reply["stereo_bias"])
    dems = [read_geotiff(p / "dem.tif")[0] for p in (source, remapped)]
    assert np.array_equal(dems[0], dems[1], equal_nan=True)
