"""grab-tof and grab-stereo against a real server on the simulated test bed: products, truth, errors."""
from __future__ import annotations

import json

import numpy as np
import tifffile

from rvs_server.products.rasters import read_png

from conftest import pairs


# The three grab tests share one server: each names its own products and points the PTU itself where
# its assertions depend on where it looks (grab-tof's tilt); none changes a config or leaves a job.
def test_grab_tof_writes_raw_values_a_picture_and_the_truth(shared_server):
    with shared_server.connect() as c:
        assert c.command("move-ptu --tilt -35 --speed 50").split()[1] == "OK"
        reply = pairs(c.command("grab-tof --output scan --frames 3 --min-confidence 2000", timeout=120))
    product = shared_server.data_dir / "products" / reply["product"]
    manifest = json.loads((product / "product.json").read_text())
    assert manifest["status"] == "complete" and manifest["command"] == "grab-tof"
    assert manifest["arguments"]["frames"] == 3
    distance = tifffile.imread(product / "distance.tif")
    assert distance.dtype == np.uint16 and distance.shape == (144, 176)
    picture = read_png(product / "distance.png")
    assert picture.shape[0] > 144 and picture.shape[2] == 3  # enlarged, with a legend strip
    frame = json.loads((product / "frame.json").read_text())
    truth_range = tifffile.imread(product / "truth" / "range.tif")
    state = json.loads((product / "truth" / "state.json").read_text())
    assert abs(state["ptu"]["tilt_deg"] + 35) < 0.06
    # what the camera measured agrees with the truth where it is defined and inside the unambiguous range
    metres = distance.astype(np.float64) * frame["non_ambiguity_range_m"] / 65535
    usable = (distance > 0) & (truth_range < frame["non_ambiguity_range_m"] - 0.2)
    assert usable.mean() > 0.5
    error = np.abs(metres[usable] - truth_range[usable])
    assert np.median(error) < 0.03


def test_grab_tof_xyz_and_a_name_that_is_a_path(shared_server):
    with shared_server.connect() as c:
        reply = pairs(c.command("grab-tof --output xyz1 --image xyz", timeout=120))
        xyz = tifffile.imread(shared_server.data_dir / "products" / reply["product"] / "xyz.tif")
        assert xyz.shape == (144, 176, 3) and xyz.dtype == np.float32
        assert "ERR 400" in c.command("grab-tof --output ../escape")
        assert "ERR 400" in c.command("grab-tof --output .hidden")
        assert not (shared_server.data_dir.parent / "escape").exists()
        # the same name twice makes a second product, never overwrites the first
        assert pairs(c.command("grab-tof --output xyz1", timeout=120))["product"] == "xyz1-2"


def test_grab_stereo_takes_both_images_at_one_instant(shared_server):
    with shared_server.connect() as c:
        reply = pairs(c.command("grab-stereo --output pair", timeout=120))
    product = shared_server.data_dir / "products" / reply["product"]
    frames = json.loads((product / "frames.json").read_text())
    assert frames["left"]["timestamp_s"] == frames["right"]["timestamp_s"]
    left, right = read_png(product / "left.png"), read_png(product / "right.png")
    assert left.shape == right.shape == (540, 960)
    assert left.std() > 10 and not np.array_equal(left, right)  # textured, and two viewpoints
    assert (product / "truth" / "state.json").exists()


def test_status_reports_every_device_and_faults_are_503(server_factory):
    server = server_factory(configs={"devices.toml": "[tof]\nenabled = false\n[cameras]\nenabled = false\n"})
    with server.connect() as c:
        status = pairs(c.command("status"))
        assert status["dev.ptu"] == "ok" and status["dev.tof"] == "off" and status["dev.camera_left"] == "off"
        assert "ERR 503 device tof is off" in c.command("grab-tof --output a")
        assert "ERR 503 device cameras is off" in c.command("grab-stereo --output b")
        assert c.command("status").split()[1] == "OK"


def test_a_missing_vendor_library_is_a_precise_503(server_factory, tmp_path):
    missing = tmp_path / "no-such-libmesasr.so"
    server = server_factory(configs={"devices.toml": f'[tof]\nbackend = "mesa"\nlibrary = "{missing}"\n'})
    with server.connect() as c:
        status = pairs(c.command("status"))
        assert status["dev.tof"] == "fault"
        reply = c.command("grab-tof --output a")
        assert "ERR 503 device tof is fault" in reply and "no-such-libmesasr.so" in reply


def test_a_saved_world_is_loaded_with_world_file(server_factory, tmp_path):
    import subprocess
    import sys

    from conftest import REPO, SMALL_WORLD
    (tmp_path / "w.toml").write_text(SMALL_WORLD.replace("seed = 3", "seed = 9"))
    saved = tmp_path / "scene.npz"
    subprocess.run([sys.executable, "-m", "drivers.sim", "save", str(saved), "--config", str(tmp_path / "w.toml")],
                   cwd=REPO, check=True, capture_output=True, timeout=120)
    server = server_factory(args=["--world", str(saved)])
    with server.connect() as c:
        reply = pairs(c.command("grab-tof --output fromfile", timeout=120))
    state = json.loads((server.data_dir / "products" / reply["product"] / "truth" / "state.json").read_text())
    assert state["world"]["file"] == str(saved)
