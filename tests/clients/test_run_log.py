"""The campaigns' results file (clients/run_log.py) and the reports read from it alone: a run is
durable the moment it is appended, a rerun with the same settings skips it, other settings do not,
a run that broke is tried again, a line cut short by a kill is ignored, and the orient and
navigation campaign scripts print their summary tables from the file."""
from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

from clients.run_log import RunLog, group_by_settings, read_runs

REPO = Path(__file__).resolve().parents[2]


def load_bench(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "tests" / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_runs_are_kept_skipped_on_rerun_and_a_cut_line_is_ignored(tmp_path):
    path = tmp_path / "results" / "campaign.jsonl"
    split = RunLog(path, {"length_m": 30.0, "max_turn_deg": 15.0})
    unsplit = RunLog(path, {"length_m": 30.0, "max_turn_deg": 90.0})
    planned = [{"seed": seed, "sensor": sensor} for sensor in ("stereo", "tof") for seed in (1, 2)]
    assert split.todo(planned) == planned                       # no file yet: everything to do

    split.append({"seed": 1, "sensor": "stereo"}, 61.5, end_pct=0.4)
    split.append({"sensor": "tof", "seed": 2}, 70.0, end_pct=0.6)   # key order does not matter
    split.append({"seed": 2, "sensor": "stereo"}, 3.0, error="RuntimeError('server did not start')")
    with open(path, "a") as f:                                   # a kill in the middle of a write
        f.write('{"run": {"seed": 1, "sensor": "tof"}, "settings": {"length_m": 30.0, "max')

    assert [r["run"] for r in read_runs(path)] == [{"seed": 1, "sensor": "stereo"}, {"sensor": "tof", "seed": 2},
                                                   {"seed": 2, "sensor": "stereo"}]
    # done: the two that finished; the broken one and the cut one are run again
    assert split.todo(planned) == [{"seed": 2, "sensor": "stereo"}, {"seed": 1, "sensor": "tof"}]
    assert unsplit.todo(planned) == planned                      # other settings: nothing of theirs is done
    # the rerun's good line for the broken run replaces it
    split.append({"seed": 2, "sensor": "stereo"}, 58.0, end_pct=0.5)
    assert sorted((r["run"]["seed"], "error" in r) for r in split.runs() if r["run"]["sensor"] == "stereo") == \
        [(1, False), (2, False)]
    [(settings, runs)] = group_by_settings(read_runs(path))
    assert settings == {"length_m": 30.0, "max_turn_deg": 15.0} and len(runs) == 3


def fake_traverse(seed: int, drift: float) -> list[dict]:
    """Looks along a straight 12 m line east, the estimate off by `drift` of the distance sideways."""
    looks = []
    for i in range(13):
        x = float(i)
        looks.append({"true": (x, 0.0, 0.0), "estimate": (x, drift * x, 0.0), "dead_reckoning": (x, 0.02 * x, 0.01 * i),
                      "driven": x, "wall_ms": 800.0 + seed, "odometry_ms": 300.0, "sigma_xy": 0.05,
                      "sigma_heading": 0.001, "rekeyed": i % 3 == 0, "sources": "vo,sun", "inliers": 200,
                      "method": "stereo"})
    return looks


def test_the_orient_campaign_reports_from_its_file_alone(tmp_path):
    orient = load_bench("orient_campaign")
    path = tmp_path / "orient.jsonl"
    log = RunLog(path, {"length_m": 12.0, "max_turn_deg": 15.0})
    for seed, drift in ((1, 0.004), (2, 0.006)):
        result = {"seed": seed, "sensor": "stereo", "calls": 14,
                  "failures": [] if seed == 1 else ["ERR 400 no-overlap"],
                  "looks": fake_traverse(seed, drift)}
        record = log.append({"seed": seed, "sensor": "stereo"}, 60.0, **orient.scores(result),
                            failures=result["failures"], looks=result["looks"])
        assert math.isclose(record["orient_seg5m_pct"], 100 * drift, rel_tol=1e-3)
    log.append({"seed": 3, "sensor": "stereo"}, 1.0, error="RuntimeError('no product')")

    printed = subprocess.run([sys.executable, str(REPO / "tests" / "bench" / "orient_campaign.py"),
                              "--report", str(path)],
                             capture_output=True, text=True, timeout=120, check=True).stdout
    assert "== length_m=12.0 max_turn_deg=15.0: 2 runs" in printed
    assert "stereo: 2 traverses, 26 looks" in printed
    assert "5 m: median 0.50 %" in printed                     # the two runs' segments pooled: 0.4 and 0.6 %
    assert "converged 27/28 = 96.43 %" in printed
    assert "stereo seed 3 broke: RuntimeError('no product')" in printed


def test_the_navigation_campaign_reports_from_its_file_alone(tmp_path):
    path = tmp_path / "navigation.jsonl"
    for orient, error in (("off", 0.30), ("on", 0.05)):
        log = RunLog(path, {"size_m": 34.0, "orient": orient})
        for seed in (101, 102):
            log.append({"seed": seed, "sensor": "tof"}, 120.0, cover=0.17, goal=[9.0, 3.0], optimal_m=10.0,
                       goal_clearance_m=0.8, ok=True, outcome="arrived", true_distance_to_goal=0.1, success=True,
                       contacts=0, driven_m=11.0, length_ratio=1.1, localisation_error_m=error,
                       odometry_error_m=0.3, cycles=4, looks=3 if orient == "on" else 0, looks_failed=0,
                       product="p", reply="OK")
    printed = subprocess.run([sys.executable, str(REPO / "tests" / "bench" / "measure_navigation.py"), "--report",
                              str(path)], capture_output=True, text=True, timeout=120, check=True).stdout
    off, on = printed.split("== orient=on")
    assert "== orient=off size_m=34.0: 2 runs" in off and "median 30.0 cm" in off
    assert "median 5.0 cm" in on and "success 2/2" in on and "orient looks per run median 3" in on
    assert json.loads(path.read_text().splitlines()[0])["run"] == {"seed": 101, "sensor": "tof"}


def test_config_settings_of_a_campaign_are_parsed_applied_and_refused_by_name(tmp_path):
    import tomllib

    import pytest

    from clients.campaign import override_config
    from clients.run_log import config_overrides

    from conftest import write_configs

    overrides = config_overrides(["orient.toml:sensor='tof'", "navigation.toml:orient={tof=true, stereo=false}",
                                  "orient.toml:stereo.max_features=900"])
    assert overrides == {"orient.toml": {"sensor": "tof", "stereo": {"max_features": 900}},
                         "navigation.toml": {"orient": {"tof": True, "stereo": False}}}
    configs = write_configs(tmp_path / "configs", {})
    override_config(configs, "navigation.toml", overrides["navigation.toml"])
    assert tomllib.loads((configs / "navigation.toml").read_text())["orient"] == {"tof": True, "stereo": False}

    for bad, says in (("orient.toml:sensor=tof", "not a TOML value"), ("orient.toml sensor=1", "FILE.toml:KEY=VALUE"),
                      ("orient:sensor=1", "FILE.toml:KEY=VALUE"), ("orient.toml:=1", "FILE.toml:KEY=VALUE")):
        with pytest.raises(ValueError, match=says) as error:
            config_overrides([bad])
        assert repr(bad) in str(error.value)
