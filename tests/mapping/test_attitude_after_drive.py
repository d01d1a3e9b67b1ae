"""A map made after a drive on a slope: the estimate's roll and pitch are the ones where the rover
stands (the inclinometer) and its height climbed along the pitch it read on the way, so
dem-update-tof's new cells agree with the truth as on flat ground."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rvs_server.products.rasters import read_geotiff
from toolbox.grid import GridSpec

from conftest import pairs

# A plane falling 12 degrees toward the south, no undulation: the rover starts facing east (along the
# contour: its left side up 12 degrees); a quarter turn left faces it up the slope (nose up 12
# degrees), so roll and pitch trade places while x, y and z stay where they were.
SLOPE_WORLD = """seed = 5
size_m = [12.0, 12.0]
[terrain]
slope_deg = 12.0
slope_azimuth_deg = 180.0
undulation_rms_m = 0.0
[rocks]
cover = 0.03
[craters]
count = 0
"""
FLAT_GROUND_RMS_M = 0.05   # tests/mapping/test_mapping_commands.py: a dem-full-tof against its truth


def tilt_error_deg(product) -> float:
    """The largest angle, over the views, between the world's vertical as the estimated camera pose
    and as the true one see it: the attitude error the map inherits (heading errors do not count)."""
    estimated = json.loads((product / "views.json").read_text())
    true = json.loads((product / "truth" / "views.json").read_text())
    worst = 0.0
    for view, truth in zip(estimated, true, strict=True):
        up_estimated = np.asarray(view["camera_to_world"])[:3, :3].T @ [0.0, 0.0, 1.0]
        up_true = np.asarray(truth)[:3, :3].T @ [0.0, 0.0, 1.0]
        worst = max(worst, math.degrees(math.acos(float(np.clip(up_estimated @ up_true, -1.0, 1.0)))))
    return worst


def new_cells(update, before) -> np.ndarray:
    """Cells of the update that the map before it did not know (both grids share cell boundaries)."""
    dem, spec = read_geotiff(update / "dem.tif")
    old, old_spec = read_geotiff(before / "dem.tif")
    xs, ys = GridSpec.from_json(json.loads((update / "grid.json").read_text())).centres()
    rows, cols, inside = old_spec.cell_of(*np.meshgrid(xs, ys))
    known_before = np.zeros(dem.shape, dtype=bool)
    known_before[inside] = np.isfinite(old[rows[inside], cols[inside]])
    return np.isfinite(dem) & ~known_before


def test_a_map_after_a_turn_on_a_slope_is_level_with_the_truth(server_factory):
    server = server_factory(configs={"world.toml": SLOPE_WORLD})
    products = server.data_dir / "products"
    with server.connect() as c:
        pairs(c.command("dem-full-tof --pan -40:40 --output before", timeout=300))
        assert " OK " in c.command("drive --turn 90", timeout=300)
        pairs(c.command("dem-update-tof --pan -30:30 --output after", timeout=300))
    before, after = products / "before", products / "after"
    assert tilt_error_deg(before) < 0.5            # the start pose is given: the control
    assert tilt_error_deg(after) < 0.5             # 17 degrees when the drive kept the attitude from before it
    new = new_cells(after, before)
    assert new.sum() > 500
    dem = read_geotiff(after / "dem.tif")[0]
    truth = read_geotiff(after / "truth" / "height.tif")[0]
    error = (dem - truth)[new]
    assert np.sqrt(np.mean(error ** 2)) < FLAT_GROUND_RMS_M


def new_cells_error(after, before) -> np.ndarray:
    """The update's height error (estimate - truth) on the cells the map before it did not know."""
    new = new_cells(after, before)
    assert new.sum() > 500
    dem = read_geotiff(after / "dem.tif")[0]
    truth = read_geotiff(after / "truth" / "height.tif")[0]
    return (dem - truth)[new]


@pytest.mark.parametrize("turn", [90, -90], ids=["uphill", "downhill"])
def test_a_map_after_driving_up_or_down_a_slope_is_at_the_true_height(server_factory, turn):
    # Facing up (north) or down (south) the 12-degree plane, 1.5 m forward rises or falls 0.32 m:
    # the map was built that much off when the drive kept the height from before it.
    server = server_factory(configs={"world.toml": SLOPE_WORLD})
    products = server.data_dir / "products"
    with server.connect() as c:
        pairs(c.command("dem-full-tof --pan -40:40 --output before", timeout=300))
        assert " OK " in c.command(f"drive --turn {turn}", timeout=300)
        assert " OK " in c.command("drive --forward 1.5", timeout=300)
        pairs(c.command("dem-update-tof --pan -30:30 --output after", timeout=300))
    before, after = products / "before", products / "after"
    assert tilt_error_deg(after) < 0.5
    error = new_cells_error(after, before)
    assert abs(error.mean()) < FLAT_GROUND_RMS_M / 2   # 0.32 m low uphill (high downhill) with the old height
    assert np.sqrt(np.mean(error ** 2)) < FLAT_GROUND_RMS_M
