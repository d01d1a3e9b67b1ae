"""The measurement campaigns of tests/bench/campaigns beside navigation (maps, hopping, routes) and their
scoring shared with the scripts (tests/bench/*_scoring.py), fast: the files parse and name the scripts'
runs, their execute hooks call what the scripts call, and the hooks give the expected figures on
products and records written by hand."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from clients import campaign as C
from rvs_server.products.rasters import write_geotiff
from toolbox.grid import GridSpec

from conftest import REPO

BENCH = REPO / "tests" / "bench"
CAMPAIGNS = BENCH / "campaigns"
M = C._hook_module(str(BENCH / "maps_scoring.py"))      # as a campaign's hooks load them
H = C._hook_module(str(BENCH / "hopping_scoring.py"))
R = C._hook_module(str(BENCH / "routes_scoring.py"))


# -- maps ----------------------------------------------------------------------------------------------------


def test_the_maps_campaign_file_runs_the_scripts_seeds_with_its_mission():
    loaded = C.load_campaign(CAMPAIGNS / "maps.toml")
    assert loaded.runs == [{"seed": seed} for seed in (1, 2, 3, 4, 5)]   # measure_maps.py --seeds' default
    assert loaded.sim_speed == 100.0                                      # and its --sim-speed
    lines = C.mission.parse_mission(loaded.mission_text, C.variables_of(loaded.runs[0], "r", 1))
    assert [line.command for line in lines] == ["@tof dem-full-tof --output tof", "@stereo dem-full --output stereo"]
    assert loaded.score.endswith("maps_scoring.py:score") and loaded.report.endswith("maps_scoring.py:report")


def dem_product(product: Path, offset: float, hazard_on_rock: bool, false_hazard: bool = False) -> Path:
    """A 2 m x 2 m product: the DEM `offset` above the truth over its western half, one 0.3 m rock."""
    spec = GridSpec(-1.0, -1.0, 0.1, 20, 20)
    truth = np.zeros(spec.shape)
    obstacles = np.zeros(spec.shape)
    obstacles[8:11, 4:7] = 1.0                        # a rock in the observed half
    dem = np.full(spec.shape, np.nan)
    dem[:, :10] = truth[:, :10] + offset
    hazard = np.where(np.isfinite(dem), 0.0, 255.0)
    if hazard_on_rock:
        hazard[8:11, 4:7] = 1.0
    if false_hazard:
        hazard[0, 0] = 3.0                            # far from the rock: a false hazard
    (product / "truth").mkdir(parents=True)
    write_geotiff(product / "dem.tif", dem, spec)
    write_geotiff(product / "hazard.tif", hazard, spec)
    write_geotiff(product / "truth" / "height.tif", truth, spec)
    write_geotiff(product / "truth" / "obstacles.tif", obstacles, spec)
    (product / "truth" / "state.json").write_text(json.dumps({"rover": {"x": 0.0, "y": 0.0}}))
    (product / "product.json").write_text(json.dumps({"timings_s": {"acquired": 3.5, "total": 6.0}}))
    return product


def test_maps_scores_and_report_from_the_products(tmp_path):
    data = tmp_path / "data"
    dem_product(data / "products" / "tof", 0.01, hazard_on_rock=True)
    dem_product(data / "products" / "stereo", -0.02, hazard_on_rock=False, false_hazard=True)
    values = M.score({"seed": 3}, data)
    assert values["tof_rmse"] == pytest.approx(0.01, abs=1e-6) and values["tof_bias"] == pytest.approx(0.01, abs=1e-6)
    assert values["tof_recall"] == 1.0 and values["tof_rocks"] == 1 and values["tof_false_hazard"] == 0.0
    assert values["stereo_bias"] == pytest.approx(-0.02, abs=1e-6) and values["stereo_recall"] == 0.0
    safe = 200 - (5 * 5 - 4)            # the observed half less the 3x3 rock grown by one 0.1 m cell (a cross)
    assert values["stereo_false_hazard"] == pytest.approx(1 / safe)
    disc = np.hypot(*np.meshgrid(np.arange(-0.95, 1.0, 0.1), np.arange(-0.95, 1.0, 0.1))) <= 4.5
    assert values["tof_observed"] == pytest.approx(disc[:, :10].sum() / disc.sum())     # half of the disc
    assert values["tof_timings_s"] == {"acquired": 3.5, "total": 6.0} and math.isnan(values["peak_memory_mib"])
    # All of this product lies within 4 m of the rover: the near figures are the whole disc's.
    assert values["tof_rmse_4m"] == pytest.approx(values["tof_rmse"]) and values["tof_rocks_4m"] == 1
    assert values["tof_recall_4m"] == 1.0 and values["stereo_false_hazard_4m"] == values["stereo_false_hazard"]
    text = M.report([{"run": {"seed": 3}, "values": values},
                     {"run": {"seed": 1}, "values": {**values, "tof_rmse": 0.03}}]).splitlines()
    assert text[0] == ("seed 1 tof    rmse  3.00 cm  p95  1.00 cm  bias +1.00 cm  observed 0.50  recall 1.00 "
                       "(1 rocks)  false hazard 0.000")                 # sorted by seed, the script's line
    assert text[2] == ("seed 1 dem-full-tof seconds: acquired 3.50, total 6.00; server peak memory nan MiB "
                       "(world included)")
    assert text[-2].startswith("mean tof    rmse  2.00 cm") and text[-1].startswith("mean stereo rmse  2.00 cm")


# -- hopping -------------------------------------------------------------------------------------------------


def test_the_hopping_campaign_file_makes_the_scripts_runs_and_plays_them_as_the_script_does(tmp_path, monkeypatch):
    loaded = C.load_campaign(CAMPAIGNS / "hopping.toml")
    assert loaded.runs == H.runs() and loaded.sim_speed == 100.0             # measure_hopping.py's defaults
    assert loaded.execute.endswith("hopping_scoring.py:execute") and loaded.report.endswith("hopping_scoring.py:report")
    chains = [r for r in loaded.runs if r["kind"] == "chain"]
    singles = [r for r in loaded.runs if r["kind"] == "singles"]
    assert [r["seed"] for r in chains] == [301, 302, 303, 304, 305] and {r["hops"] for r in chains} == {5}
    assert [(r["seed"], r["hops"], r["spin"]) for r in singles] == [(401, 15, 20.0), (402, 15, 20.0)]  # 30 over 2
    assert {(r["size"], r["cover"]) for r in loaded.runs} == {(30.0, 0.07)} and "octave" not in chains[0]
    assert H.runs(octave=0, kinds=["chains"], scenes=1) == [{"seed": 301, "kind": "chain", "hops": 5, "size": 30.0,
                                                              "cover": 0.07, "octave": 0}]
    # execute calls what measure_hopping.py calls, with the script's arguments: the same server, the same hops.
    calls = []
    monkeypatch.setattr(H, "chain", lambda *args: calls.append(("chain", *args)) or {"kind": "chain"})
    monkeypatch.setattr(H, "singles", lambda *args: calls.append(("singles", *args)) or {"kind": "singles"})
    assert H.execute(chains[0], tmp_path, 100.0) == {"kind": "chain"}
    assert H.execute(singles[1], tmp_path, 100.0) == {"kind": "singles"}
    assert calls == [("chain", 301, tmp_path, 5, 30.0, 0.07, 100.0, None),
                     ("singles", 402, tmp_path, 15, 30.0, 0.07, 100.0, 20.0, None)]
    with pytest.raises(ValueError, match="kind 'hop'"):
        H.execute({"kind": "hop"}, tmp_path, 1.0)


def hop(launch, landing, touchdown, corrected, target=None, icp=None, before=((0, 0), (0, 0))):
    return {"truth": {"launch": {"centre_m": [*launch, 0.0]}, "landing": {"centre_m": [*landing, 0.0]}},
            "touchdown_m": [*touchdown, 0.0], "launch_corrected_m": [*corrected, 0.0], "icp": icp or {},
            "target_m": target, "frames": 50, "registered": 50, "seconds": 3.0,
            "timings_s": {"sfm": 2.0, "write": 0.5},
            "comparison": {"next_launch": {"bounce_horizontal_m": 0.2},
                           "launch_before_icp": {"true_m": list(before[0]), "estimated_m": list(before[1])},
                           "target": {"footprint_clear": True, "nearest_true_obstacle_m": 0.5}}}


def test_hopping_chain_and_single_figures_from_hand_made_records():
    icp = {"used": True, "shift_m": [0.05, 0.0], "match": {"shift_m": [0.04, 0.0]}, "icp": {"shift_m": [0.05, 0.0]}}
    chain = {"kind": "chain", "seed": 301, "peak_memory_mib": 900.0, "stopped": None,
             "hops": [hop((0, 0), (1, 0), (1.01, 0), (0, 0), target=[2.0, 0.0]),
                      hop((1.2, 0), (2, 0), (2.02, 0), (1.2, 0), icp=icp, before=((1.2, 0), (1.15, 0)))]}
    rows = H.chain_errors(chain)
    assert [round(r["with_icp_pct"], 3) for r in rows] == [1.0, 1.0]
    assert [round(r["without_icp_pct"], 3) for r in rows] == [1.0, 8.5]     # (1.01 + 0.82) m for 2 m
    assert rows[0]["next_touchdown_from_target_m"] == 0.0
    assert rows[1]["match_error_m"] == pytest.approx(0.01) and rows[1]["applied_error_m"] == pytest.approx(0.0)
    single = hop((0, 0), (3, 0), (3.06, 0), (0, 0))
    singles = {"kind": "singles", "seed": 401, "peak_memory_mib": 950.0,
               "hops": [{**single, "commanded_m": 3.0}, {"plan_error": "503 no-overlap", "commanded_m": 9.0}]}
    assert H.single_errors(singles)[0]["displacement_error_pct"] == pytest.approx(2.0)
    text = H.report([{"run": {"seed": 301}, "values": chain}, {"run": {"seed": 401}, "values": singles}])
    assert "all hops: with ICP mean 1.00 %, max 1.00 %; without mean 4.75 %, max 8.50 %" in text
    assert "hop displacement error: mean 2.00 %, median 2.00 %, max 2.00 %; over 4 %: 0" in text
    assert "failed: 9.0 m: 503 no-overlap" in text and "peak resident memory of the server: max 950 MiB" in text
    assert text == H.summary([chain, singles])                 # measure_hopping.py's report, from the same code


# -- routes --------------------------------------------------------------------------------------------------


def test_the_routes_campaign_file_makes_a_run_per_scene_played_as_the_script_does(tmp_path, monkeypatch):
    loaded = C.load_campaign(CAMPAIGNS / "routes.toml")
    assert loaded.runs == R.runs() and len(loaded.runs) == 10 and loaded.sim_speed == 50.0
    assert loaded.runs[0] == {"seed": 501, "matchers": ["features", "contour"], "suns": ["same", "moved"],
                              "orient": "off", "network": True}
    assert loaded.execute.endswith("routes_scoring.py:execute") and loaded.report.endswith(":campaign_report")
    assert R.runs(scenes=1, orient="both", network=False)[0]["orient"] == "both"
    with pytest.raises(ValueError, match="orient 'sideways'"):
        R.runs(orient="sideways")
    # execute calls scene() as measure_routes.py does, at the campaign's speed, and counts the successes.
    calls = []
    rows = [{"length_m": 30.0, "success": True}, {"length_m": 30.0, "success": False}]
    monkeypatch.setattr(R, "scene", lambda *args: calls.append(args) or rows)
    values = R.execute(R.runs(scenes=1, orient="both", network=False)[0], tmp_path, 50.0)
    assert calls == [(501, tmp_path, ("features", "contour"), ("same", "moved"), (False, True), False)]
    assert values == {"length_m": 30.0, "repeats": 2, "successes": 1, "results": rows}
    assert R._conftest().SIM_SPEED == 50.0


def test_route_chords_keep_clear_of_blocked_cells():
    blocked = np.zeros((40, 40), bool)
    blocked[10:30, 20] = True                     # a wall the straight line would cross
    cells = np.array([[20, c] for c in range(0, 18)] + [[r, 18] for r in range(21, 36)]
                     + [[35, c] for c in range(19, 39)])
    kept = R.chords(cells, blocked, 50.0)
    assert kept[0].tolist() == [20, 0] and kept[-1].tolist() == [35, 38]
    assert all(R.segment_is_clear(blocked, p, q) for p, q in zip(kept[:-1], kept[1:], strict=True))
    assert len(R.chords(cells, blocked, 5.0)) > len(kept)          # shorter legs: more of them


def follow_product(product: Path, path, images: int) -> Path:
    (product / "truth").mkdir(parents=True)
    (product / "truth" / "path.json").write_text(json.dumps({"path": path}))
    (product / "follow.json").write_text(json.dumps({"images": images, "orient_looks": 2, "orient_refused": [1],
                                                     "segments": [{"last_matched": 7}]}))
    return product


def test_routes_scores_and_table_from_the_products(tmp_path):
    taught = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [10.0, 0.0, 0.0]]
    good = R.score_product(follow_product(tmp_path / "a", [[0, 0.1, 0], [5, 0.3, 0], [9.8, 0.0, 0]], 40),
                           np.array(taught[-1]), taught, ok=True)
    assert good["success"] and good["final_m"] == 0.2 and good["max_deviation_m"] == 0.3
    assert good["images"] == 40 and good["orient_refused"] == 1 and good["last_matched"] == 7
    short = R.score_product(follow_product(tmp_path / "b", [[0, 0, 0], [9.0, 0.0, 0]], 30),
                            np.array(taught[-1]), taught, ok=True)
    assert not short["success"] and short["final_m"] == 1.0
    rows = [{"seed": 501, "matcher": "features", "sun": "same", "direction": "forward", "orient": False,
             "length_m": 10.0, "bytes_per_m": 2048.0, **good},
            {"seed": 502, "matcher": "features", "sun": "same", "direction": "forward", "orient": False,
             "length_m": 10.0, "bytes_per_m": 2048.0, **short}]
    text = R.campaign_report([{"run": {"seed": 501}, "values": {"results": rows[:1]}},
                              {"run": {"seed": 502}, "values": {"results": rows[1:]}}])
    assert text == R.report(rows)                 # measure_routes.py's table, from the same code
    assert text.splitlines()[0] == "2 scenes, routes 10.0-10.0 m, 2.0 KiB stored per metre (mean)"
    assert text.splitlines()[2].split()[:6] == ["features", "same", "forward", "off", "1/2", "0.60"]
