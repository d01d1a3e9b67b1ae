"""`rvs remap`: a stored dem-full-tof product re-mapped with a stricter workflow, on a Dask
LocalCluster, with no server and no device: the same DEM, a larger hazardous share, the source named."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from clients.cli import main as rvs

from conftest import REPO, one_product

STRICT_STEP = 0.03     # m; mapping.toml's step_limit is 0.10


def strict_workflow(folder: Path) -> Path:
    text = (REPO / "workflows" / "dem-full-tof.yaml").read_text()
    assert "step_limit: $config.step_limit" in text
    path = folder / "dem-full-tof-strict.yaml"
    path.write_text(text.replace("step_limit: $config.step_limit", f"step_limit: {STRICT_STEP}"))
    return path


def manifest(product: Path) -> dict:
    return json.loads((product / "product.json").read_text())


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """One dem-full-tof product made by a real server, which is then stopped."""
    root = tmp_path_factory.mktemp("remap")
    _, reply = one_product(root, "dem-full-tof --pan -40:40 --output scan")
    return root, Path(reply["path"]), reply


def test_a_stored_map_remapped_stricter_on_dask_with_no_device(stored, capfd):
    root, source, reply = stored
    files = manifest(source)["files"]
    assert {"views/acquire_tof.npz", "views/views_plan.npz", "views/context.json"} <= set(files)
    workflow = strict_workflow(root)

    assert rvs(["remap", str(source), "--workflow", str(workflow), "--workers", "1"]) == 0
    line = capfd.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("scan -> scan-remap known "), line
    remapped = source.parent / "scan-remap"
    made = manifest(remapped)
    assert made["status"] == "complete" and made["command"] == "dem-full-tof"
    assert made["source"]["product"] == "scan" and made["source"]["path"] == str(source.resolve())
    hazard_step = next(s for s in made["workflow"]["steps"] if s["op"] == "hazard.maps")
    assert hazard_step["params"]["step_limit"] == STRICT_STEP
    assert [s["step"] for s in made["workflow"]["steps"] if s.get("resumed")] == ["views", "acquired"]

    # The same DEM, cell for cell; more of it hazardous under the stricter step limit.
    before, after = tifffile.imread(source / "dem.tif"), tifffile.imread(remapped / "dem.tif")
    assert np.array_equal(before, after, equal_nan=True)
    assert json.loads((source / "grid.json").read_text()) == json.loads((remapped / "grid.json").read_text())
    hazardous = float(line.split("hazardous ")[1].split()[0])
    assert hazardous > float(reply["hazardous"]) + 0.005, (hazardous, reply["hazardous"])
    # The truth grids come along (same grid), and the new product keeps the views in turn.
    assert (remapped / "truth" / "height.tif").is_file()
    assert (remapped / "views" / "acquire_tof.npz").is_file()


def test_remap_refuses_what_it_cannot_do_and_writes_nothing(stored, tmp_path, capfd):
    root, source, _ = stored
    products = source.parent
    before = sorted(p.name for p in products.iterdir())

    update = REPO / "workflows" / "dem-update-tof.yaml"      # merges the previous map: not in the views
    stereo = REPO / "workflows" / "dem-full.yaml"            # stereo views were not taken
    broken = tmp_path / "broken.yaml"
    broken.write_text((REPO / "workflows" / "dem-full-tof.yaml").read_text().replace("op: dem.grid", "op: dem.gird"))
    from rvs_server.mapping.remap import RemapError, remap
    for workflow, expected in ((update, "dem.merge_last"), (stereo, "acquire.stereo"), (broken, "dem.gird")):
        with pytest.raises(RemapError, match=expected.replace(".", r"\.")):
            remap(source, workflow)
    with pytest.raises(RemapError, match="no stored views"):
        remap(_bare(tmp_path), stereo)
    assert sorted(p.name for p in products.iterdir()) == before

    assert rvs(["remap", str(tmp_path / "nothing"), "--workflow", str(update)]) == 2
    assert "not a product folder" in capfd.readouterr().err


def _bare(folder: Path) -> Path:
    """A product folder without stored views (as products made before they were kept)."""
    product = folder / "old"
    product.mkdir()
    (product / "product.json").write_text(json.dumps({"name": "old", "command": "dem-full-tof", "status": "complete"}))
    return product
