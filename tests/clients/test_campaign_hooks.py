"""A measurement campaign's hooks (clients/campaign.py: runs_from, score, report; a run's own world and
configs) and the navigation campaign's scoring (tests/bench/navigation_scoring.py), without Dask: one run
played in-process as a worker would, and the scores of a navigate product written by hand."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from clients import campaign as C

from conftest import REPO

CAMPAIGNS = REPO / "tests" / "bench" / "campaigns"
N = C._hook_module(str(REPO / "tests" / "bench" / "navigation_scoring.py"))   # as the campaign's hooks load it

SCENES = {"34": {"101": {"goal": [5.5, -8.25], "optimal_m": 11.0, "goal_clearance_m": 0.9, "cover": 0.17},
                 "102": False,
                 "103": {"goal": [-9.0, 3.0], "optimal_m": 10.2, "goal_clearance_m": 0.7, "cover": 0.16}}}


def test_a_run_brings_its_own_world_and_settings_and_is_scored_in_the_worker(tmp_path, monkeypatch):
    """execute_run (a Dask task's body) merges the run's `world` and `configs` over the campaign's, and
    adds what the score hook gives to the collected values."""
    calls = []

    def scored(run, data_dir):
        calls.append((run, data_dir))
        cells = json.loads(next(Path(data_dir, "products").glob("dem-update-tof-*/grid.json")).read_text())
        return {"cell_seen": cells["cell"], "products": len(list(Path(data_dir, "products").iterdir()))}

    monkeypatch.setattr(C, "hook", lambda spec, where: scored)
    run = {"seed": 4, "world": {"size_m": [12.0, 12.0]}, "configs": {"mapping.toml": {"cell": 0.1}},
           "PAN": 10, "TILT": -25}
    spec = {"run": run, "name": C.run_name(run), "run_dir": str(tmp_path / "run"),
            "mission_text": (REPO / "clients" / "campaigns" / "tof-look.rvs").read_text(),
            "mission_name": "tof-look.rvs", "world": {"craters": {"count": 0}},
            "collect": {"cell": "dem.cell"}, "sim_speed": 20.0, "timeout_s": 300, "score": "any:thing"}
    result = C.execute_run(spec)
    assert result["values"]["cell"] == "0.1" and result["values"]["cell_seen"] == 0.1, result
    assert result["values"]["products"] == 2 and calls[0][1] == tmp_path / "run" / "data"
    world = (tmp_path / "run" / "configs" / "world.toml").read_text()
    assert "size_m = [12.0, 12.0]" in world and "count = 0" in world    # the run's world over the campaign's


def test_the_navigation_campaign_file_names_its_runs_and_a_bad_hook_is_refused(tmp_path):
    known = tmp_path / "seeds.json"
    known.write_text(json.dumps(SCENES))
    text = (CAMPAIGNS / "navigation.toml").read_text()
    text = text.replace('known = "tests/bench/results/navigation-seeds.json"', f'known = "{known}"')
    text = text.replace("scenes = 10", "scenes = 2")
    text = text.replace("../navigation_scoring.py", str(REPO / "tests" / "bench" / "navigation_scoring.py"))
    (tmp_path / "navigation.rvs").write_text((CAMPAIGNS / "navigation.rvs").read_text())
    (tmp_path / "navigation.toml").write_text(text)
    loaded = C.load_campaign(tmp_path / "navigation.toml")
    assert len(loaded.runs) == 2 * 2 * 2      # seeds 101 and 103 (102 is boxed in), two sensors, orient off/on
    first = loaded.runs[0]
    assert first["seed"] == 101 and first["GOAL"] == "5.5,-8.25"
    assert first["world"]["rocks"] == N.scene_config(101, 34.0)["rocks"]
    assert {r["configs"]["navigation.toml"]["orient"] for r in loaded.runs} == {False, True}
    assert loaded.score == f"{REPO / 'tests' / 'bench' / 'navigation_scoring.py'}:score"
    (tmp_path / "bad.toml").write_text(text.replace("navigation_scoring.py:score", "navigation_scoring.py:nothing"))
    with pytest.raises(C.CampaignError, match="navigation_scoring.py:nothing"):
        C.load_campaign(tmp_path / "bad.toml")


def traverse(product: Path, outcome: str, end: tuple[float, float], estimate: tuple[float, float],
             contacts: int = 0) -> Path:
    (product / "truth").mkdir(parents=True)
    (product / "traverse.json").write_text(json.dumps({
        "outcome": outcome, "pose": [*estimate, 0.0, 0.0], "odometry": [end[0] + 0.3, end[1], 0.0],
        "cycle": 7, "orients": [{"cycle": 1}, {"cycle": 2, "failed": "no-overlap"}]}))
    (product / "truth" / "traverse.json").write_text(json.dumps({
        "path": [[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [end[0], end[1], 0.0]], "contacts": contacts}))
    return product


def test_navigation_scores_and_report_from_the_products(tmp_path):
    data = tmp_path / "data"
    traverse(data / "products" / "navigate-1", "arrived", (6.0, 8.0), (6.05, 8.0))
    run = {"seed": 101, "SENSOR": "tof", "GOAL": "6.0,8.1", "OPTIMAL_M": 10.0, "COVER": 0.17, "ORIENT": "on"}
    scores = N.score(run, data)
    assert scores["success"] and scores["ok"] and scores["contacts"] == 0
    assert scores["driven_m"] == pytest.approx(10.0) and scores["length_ratio"] == pytest.approx(1.0)
    assert scores["localisation_error_m"] == pytest.approx(0.05) and scores["odometry_error_m"] == pytest.approx(0.3)
    assert scores["looks"] == 2 and scores["looks_failed"] == 1
    failed = N.score_product(traverse(tmp_path / "other", "max_steps", (2.0, 2.0), (2.0, 2.1), contacts=3),
                             (6.0, 8.0), 10.0)
    assert not failed["success"] and failed["contacts"] == 3
    records = [{"run": run, "seconds": 61.0, "values": scores},
               {"run": {**run, "seed": 103}, "seconds": 80.0, "values": {**failed, "sensor": "tof", "cover": 0.16,
                                                                        "goal": [6.0, 8.0], "optimal_m": 10.0}}]
    text = N.report(records)
    assert text.startswith("== orient=on: 2 runs") and "success 1/2 (50 %)" in text and "failed: scene 103" in text
