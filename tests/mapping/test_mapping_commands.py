"""dem-full-tof and friends against a real server: products, interruption, workflows edited by hand."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from rvs_server.products.rasters import read_geotiff, read_png

from conftest import ServerProcess, pairs, write_configs

# A quarter panorama keeps these tests quick; the full one runs the same code.
ARC = "--pan -60:60 --output"


def layers(product) -> dict[str, np.ndarray]:
    return {name: read_geotiff(product / f"{name}.tif")[0]
            for name in ("dem", "slope", "step", "roughness", "hazard", "counts")}


def products(server):
    return server.data_dir / "products"


def test_dem_full_tof_writes_maps_that_agree_with_the_truth(server):
    with server.connect() as c:
        reply = pairs(c.command(f"dem-full-tof {ARC} arc", timeout=300))
    product = products(server) / reply["product"]
    manifest = json.loads((product / "product.json").read_text())
    assert manifest["status"] == "complete"
    assert [s["step"] for s in manifest["workflow"]["steps"]][:3] == ["views", "acquired", "points"]
    dem, spec = read_geotiff(product / "dem.tif")
    truth, truth_spec = read_geotiff(product / "truth" / "height.tif")
    assert spec == truth_spec and dem.dtype == np.float32
    known = np.isfinite(dem)
    assert 0.2 < known.mean() < 1.0  # the unseen stays unknown
    error = (dem - truth)[known]
    assert np.sqrt(np.mean(error ** 2)) < 0.05
    assert read_png(product / "hazard.png").shape[2] == 3
    assert (product / "cloud.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")
    views = json.loads((product / "views.json").read_text())
    assert len(views) == int(reply["views"]) and len(views) >= 3


def test_break_and_continue_give_the_same_product_as_an_uninterrupted_run(server_factory, tmp_path, uninterrupted):
    reference = uninterrupted
    interrupted = server_factory(data_dir=tmp_path / "broken")
    with interrupted.connect() as c:
        c.send(f"@d dem-full-tof {ARC} same")
        _wait_for(c, "d", "step 2/")
        brk = pairs(c.command("break", timeout=120))
        reply, _ = c.reply("d", timeout=120)
        assert "ERR 499 interrupted" in reply and brk["recovery"] == brk["job"]
        assert pairs(c.command("continue", timeout=300))["product"] == "same"
    _assert_same_maps(reference, products(interrupted) / "same")


def test_kill_restart_continue_gives_the_same_product(server_factory, tmp_path, uninterrupted):
    reference = uninterrupted
    first = server_factory(data_dir=tmp_path / "crash")
    with first.connect() as c:
        c.send(f"@d dem-full-tof {ARC} same")
        _wait_for(c, "d", "view 3/")
    first.kill()
    second = server_factory(data_dir=tmp_path / "crash")
    with second.connect() as c:
        assert pairs(c.command("status"))["recovery"] == "1"
        assert pairs(c.command("continue", timeout=300))["product"] == "same"
    _assert_same_maps(reference, products(second) / "same")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The product of a run nobody interrupts, on a fresh server with the repository's configs: what a
    resumed run must equal. The same for every resumed run, so made once for the module."""
    root = tmp_path_factory.mktemp("uninterrupted")
    plain = ServerProcess(data_dir=root / "plain", config_dir=write_configs(root / "configs")).start()
    try:
        with plain.connect() as c:
            reply = c.command(f"dem-full-tof {ARC} same", timeout=300)
    finally:
        plain.stop()
    assert " OK " in reply, reply
    return products(plain) / "same"


def _wait_for(client, tag: str, text: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = client.read_line(timeout=timeout)
        if line.startswith(f"{tag} PROGRESS") and text in line:
            return
    raise TimeoutError(text)


def _assert_same_maps(a, b) -> None:
    for name, values in layers(a).items():
        other = layers(b)[name]
        assert values.shape == other.shape, name
        assert np.array_equal(values, other, equal_nan=True), name


def test_a_workflow_edited_by_hand_changes_the_result(server_factory, tmp_path):
    server = server_factory()
    with server.connect() as c:
        base = pairs(c.command(f"dem-full-tof {ARC} base", timeout=300))
    workflow = server.config_dir.parent / "workflows" / "dem-full-tof.yaml"
    text = workflow.read_text()
    # a stricter step threshold and an extra filter step (a second hole filling, wider)
    text = text.replace("step_limit: $config.step_limit", "step_limit: 0.03")
    text = text.replace("  - name: hazard\n    op: hazard.maps\n    inputs: {dem: dem}",
                        "  - name: wider\n    op: dem.fill_holes\n    inputs: {dem: dem}\n"
                        "    params: {max_reach_cells: 8}\n"
                        "  - name: hazard\n    op: hazard.maps\n    inputs: {dem: wider}")
    workflow.write_text(text)
    with server.connect() as c:
        edited = pairs(c.command(f"dem-full-tof {ARC} edited", timeout=300))
    assert float(edited["hazardous"]) > float(base["hazardous"])
    manifest = json.loads((products(server) / "edited" / "product.json").read_text())
    assert "wider" in [s["step"] for s in manifest["workflow"]["steps"]]


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace("op: dem.grid", "op: dem.gird"), ["step 5 (grid)", "unknown operation 'dem.gird'"]),
    (lambda t: t.replace("inputs: {points: body}", "inputs: {points: nowhere}"), ["step 5 (grid)", "'nowhere'"]),
    (lambda t: t.replace("params: {cell: $args.cell,", "params: {cell: -1,"), ["step 5 (grid)", "params.cell"]),
])
def test_a_broken_workflow_is_refused_before_any_device_moves(shared_server, edit, words):
    """One server for the three edits: the workflow is read at each command, and each case puts the
    repository's file back when it is done."""
    server = shared_server
    workflow = server.config_dir.parent / "workflows" / "dem-full-tof.yaml"
    original = workflow.read_text()
    workflow.write_text(edit(original))
    try:
        with server.connect() as c:
            before = pairs(c.command("status"))
            reply = c.command(f"dem-full-tof {ARC} x", timeout=60)
            assert "ERR 400 bad-request dem-full-tof: workflow refused" in reply
            for word in words:
                assert word in reply
            assert "ERR 400" in c.command(f"check dem-full-tof {ARC} x")
            after = pairs(c.command("status"))
            assert (after["pan"], after["tilt"], after["mode"]) == (before["pan"], before["tilt"], "standby")
    finally:
        workflow.write_text(original)
    assert not (products(server) / "x").exists()


def test_stereo_dem_and_update(server):
    with server.connect() as c:
        full = pairs(c.command("dem-full --pan -30:30 --output sfull", timeout=300))
        update = pairs(c.command("dem-update-tof --pan -30:30 --output supd", timeout=300))
    assert int(full["views"]) >= 1
    manifest = json.loads((products(server) / "supd" / "product.json").read_text())
    merged = [s for s in manifest["workflow"]["steps"] if s["step"] == "merged"]
    assert merged
    dem_full, spec_full = read_geotiff(products(server) / "sfull" / "dem.tif")
    dem_upd, spec_upd = read_geotiff(products(server) / "supd" / "dem.tif")
    assert np.isfinite(dem_upd).sum() >= np.isfinite(dem_full).sum()  # the update keeps the old cells
    assert float(update["known"]) > 0
