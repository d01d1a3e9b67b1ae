"""A measurement campaign's hooks (clients/campaign.py: runs_from, score, report, execute; a run's own world
and configs) and the navigation campaign's scoring (tests/bench/navigation_scoring.py): one run played
in-process as a worker would, an execute campaign on a one-worker LocalCluster, the scores of a navigate
product written by hand, and configuration files written back as TOML."""
from __future__ import annotations

import json
import os
import tomllib
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

    def scored(run, data_dir, pid):
        calls.append((run, data_dir))
        assert str(data_dir).encode() in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")   # its server, running
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


HOOK_WITH_A_POOL = """
from concurrent.futures import ProcessPoolExecutor
from clients.campaign import call_hook

def square(value):
    return value * value

def runs():
    # max_tasks_per_child: fresh (spawned) processes, where this file's module does not exist by name
    with ProcessPoolExecutor(max_workers=2, max_tasks_per_child=1) as pool:
        found = pool.map(call_hook, [f"{__file__}:square"] * 3, [1, 2, 3])
        return [{"seed": value} for value in found]
"""


def test_a_runs_from_hook_hands_its_process_pool_functions_by_spec(tmp_path):
    """A FILE.py hook's module lives only in the process that loaded it: navigation.toml's runs_from
    built its missing worlds in a pool and broke it (BrokenProcessPool) until it passed call_hook
    the function's FILE.py:FUNCTION instead of the function."""
    (tmp_path / "pooled.py").write_text(HOOK_WITH_A_POOL)
    (tmp_path / "one.rvs").write_text("status\n")
    (tmp_path / "pooled.toml").write_text('mission = "one.rvs"\nruns_from = "pooled.py:runs"\n')
    assert [run["seed"] for run in C.load_campaign(tmp_path / "pooled.toml").runs] == [1, 4, 9]


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


# -- execute: a run played by Python instead of a mission ----------------------------------------------------

PLAYED = """\
import os
from pathlib import Path


def execute(run, run_dir, sim_speed):
    attempt = len(list(Path(run_dir).glob("attempt-*")))
    print(f"playing n={run['n']} attempt {attempt}")
    if run.get("flaky") and attempt == 1:
        raise RuntimeError("the first attempt fails")
    if run.get("broken"):
        raise RuntimeError("every attempt fails")
    if run.get("bad"):
        return [run["n"]]
    (Path(run_dir) / "played").write_text(str(attempt))
    return {"square": run["n"] ** 2, "attempt": attempt, "sim_speed": sim_speed, "pid": os.getpid()}


def report(records):
    return " ".join(f"{r['run']['n']}:{r['values']['square']}" for r in sorted(records, key=lambda r: r["run"]["n"]))


def two(run, run_dir):
    return {}
"""

EXECUTE = """\
name = "played"
execute = "played.py:execute"
report = "played.py:report"
sim_speed = 7.0

[[run]]
n = 2
[[run]]
n = 3
flaky = true
[[run]]
n = 4
"""


def played(tmp_path: Path, text: str = EXECUTE) -> Path:
    (tmp_path / "played.py").write_text(PLAYED)
    (tmp_path / "played.toml").write_text(text)
    return tmp_path / "played.toml"


def test_an_execute_campaign_runs_its_hook_per_run_retries_a_failure_once_and_resumes(tmp_path):
    loaded = C.load_campaign(played(tmp_path))
    assert loaded.execute == f"{tmp_path / 'played.py'}:execute" and loaded.mission_text == ""
    out, said = tmp_path / "out", []
    assert C.run_campaign(loaded, out, workers=1, say=said.append) == C.EXIT_OK, said
    records = {r["run"]["n"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert {n: (r["values"]["square"], r["attempts"]) for n, r in records.items()} == {2: (4, 1), 3: (9, 2), 4: (16, 1)}
    assert records[3]["values"]["attempt"] == 2 and records[2]["values"]["sim_speed"] == 7.0
    assert records[2]["values"]["pid"] != os.getpid()                  # played in a Dask worker
    flaky = out / "runs" / "n-3_flaky-True"
    assert "RuntimeError: the first attempt fails" in (flaky / "execute-1.log").read_text()   # its traceback
    assert (flaky / "execute-2.log").read_text() == "playing n=3 attempt 2\n"                 # its prints
    assert (out / "report.md").read_text() == "2:4 3:9 4:16\n"
    assert [row["status"] for row in json.loads((out / "summary.json").read_text())["runs"]] == ["ok"] * 3

    results, said = (out / "results.jsonl").read_bytes(), []
    assert C.run_campaign(C.load_campaign(tmp_path / "played.toml"), out, workers=1, say=said.append) == C.EXIT_OK
    assert "all 3 runs done already" in said[0] and (out / "results.jsonl").read_bytes() == results
    assert not (out / "runs" / "n-2" / "attempt-2").exists()


def test_an_execute_attempt_that_raises_or_gives_no_dict_fails(tmp_path):
    loaded = C.load_campaign(played(tmp_path, EXECUTE + "[[run]]\nn = 5\nbroken = true\n[[run]]\nn = 6\nbad = true\n"))
    for run, message in (({"n": 5, "broken": True}, "attempt 1: RuntimeError: every attempt fails"),
                         ({"n": 6, "bad": True}, "attempt 1: execute gave list, not a dict of values")):
        spec = {"run": run, "name": C.run_name(run), "run_dir": str(tmp_path / C.run_name(run)),
                "sim_speed": 1.0, "execute": loaded.execute}
        with pytest.raises(C.RunFailed, match=message):
            C.execute_run(spec)


@pytest.mark.parametrize(("line", "message"), [
    ('mission = "x.rvs"', r"played.toml: execute = 'played.py:execute' plays each run itself: mission cannot"),
    ('score = "played.py:report"', r"execute = 'played.py:execute' plays each run itself: score cannot"),
    ("[collect]\na = 'b.c'", r"plays each run itself: collect cannot be given"),
])
def test_an_execute_campaign_refuses_what_belongs_to_a_mission(tmp_path, line, message):
    text = EXECUTE.replace('sim_speed = 7.0', f'sim_speed = 7.0\n{line}') if "[" not in line else EXECUTE + line
    with pytest.raises(C.CampaignError, match=message):
        C.load_campaign(played(tmp_path, text))


@pytest.mark.parametrize(("value", "message"), [
    ('"played.py:nothing"', r"played.toml execute: '.*played.py:nothing': .*nothing"),
    ('"played.py:two"', r"played.toml execute: '.*played.py:two' must take \(run, run_dir, sim_speed\)"),
    ("3", r"played.toml: execute = 3: expected a string FILE.py:FUNCTION"),
    ('"nothing"', r"played.toml execute: 'nothing': expected FILE.py:FUNCTION"),
])
def test_a_bad_execute_hook_is_refused_naming_it(tmp_path, value, message):
    with pytest.raises(C.CampaignError, match=message):
        C.load_campaign(played(tmp_path, EXECUTE.replace('"played.py:execute"', value)))


def test_score_hooks_get_the_servers_pid_only_if_they_take_it():
    assert C._takes(lambda run, data_dir, pid=None: 0, "pid") and C._takes(lambda run, **more: 0, "pid")
    assert not C._takes(lambda run, data_dir: 0, "pid")      # navigation_scoring.score, as it was written


# -- configuration files written back ------------------------------------------------------------------------


def test_dump_toml_writes_hopping_toml_with_its_inline_tables_back_the_same():
    original = tomllib.loads((REPO / "configs" / "hopping.toml").read_text())
    assert isinstance(original["sfm_fallbacks"][0], dict)           # a list of inline tables
    assert tomllib.loads(C.dump_toml(original)) == original
    merged = C._merge(original, {"hopper": {"seed": 402, "launch_errors": {"spin_deg_s": 20.0}}})
    assert tomllib.loads(C.dump_toml(merged))["hopper"]["launch_errors"]["spin_deg_s"] == 20.0
    odd = {"a": [{"b": {"c d": [1, {"e": True}]}, "f": {}}], "g.h": {"i": "j"}, "k": {"l": {"m": -1.5}}}
    assert tomllib.loads(C.dump_toml(odd)) == odd
