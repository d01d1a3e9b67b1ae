"""`rvs campaign` end to end (issue 28): a 4-run campaign on a LocalCluster of 2 workers, each run a real
rvs-server; one run fails on its first attempt and passes on its retry; a rerun does nothing new."""
from __future__ import annotations

import csv
import json
import subprocess
import sys

from conftest import REPO

# ${ATTEMPT} is 1 on a run's first attempt and 2 on its retry (marker files in the run's directory under
# --out): `--pan ${PAN}e-${ATTEMPT}` is PAN/10 first and PAN/100 on the retry. PAN=2000 asks for 200
# degrees first (past the unit's 158.9: ERR 400, the mission stops, the run fails) and 20 on the retry.
MISSION = """\
status
@pan move-ptu --pan ${PAN}e-${ATTEMPT} --tilt 0
@tof grab-tof --output frame-${RUN}
"""

CAMPAIGN = """\
name = "tiny"
mission = "tiny.rvs"
sim_speed = 50.0

[world]
size_m = [12.0, 12.0]
[world.craters]
count = 0

[[run]]
seed = 1
PAN = 100
[[run]]
seed = 2
PAN = 2000
[[run]]
seed = 3
PAN = -100
[[run]]
seed = 4
PAN = 300

[collect]
mode = "status.mode"
pan = "pan.pan"
defined = "tof.defined"
product = "tof:product.json:name"
"""


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clients.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=240)


def test_campaign_retries_a_failed_run_and_resumes(tmp_path):
    (tmp_path / "tiny.rvs").write_text(MISSION)
    (tmp_path / "tiny.toml").write_text(CAMPAIGN)
    out = tmp_path / "out"
    command = ["campaign", str(tmp_path / "tiny.toml"), "--workers", "2", "--out", str(out)]

    first = run_cli(*command)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "4/4 done, 0 running, 0 failed" in first.stdout   # progress as lines (stdout is no terminal)

    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(records) == 4 and not any("error" in record for record in records)
    by_pan = {record["run"]["PAN"]: record for record in records}
    assert by_pan[2000]["attempts"] == 2   # failed once, passed on the retry
    assert abs(float(by_pan[2000]["values"]["pan"]) - 20.0) < 0.1   # the unit's resolution
    assert {pan: by_pan[pan]["attempts"] for pan in (100, -100, 300)} == {100: 1, -100: 1, 300: 1}
    assert abs(float(by_pan[100]["values"]["pan"]) - 10.0) < 0.1
    assert abs(float(by_pan[300]["values"]["pan"]) - 30.0) < 0.1
    assert all(record["values"]["mode"] == "standby" for record in records)
    assert by_pan[100]["values"]["product"] == "frame-seed-1_PAN-100"
    first_attempt = (out / "runs" / "seed-2_PAN-2000" / "mission-1.log").read_text()
    assert "ERR 400" in first_attempt and "mission stopped" in first_attempt

    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [row["status"] for row in rows] == ["ok"] * 4
    assert [row["PAN"] for row in rows] == ["100", "2000", "-100", "300"]   # the campaign's order
    assert json.loads((out / "summary.json").read_text())["runs"][1]["attempts"] == 2
    assert (out / "summary.md").read_text().count("| ok |") == 4

    results = (out / "results.jsonl").read_bytes()
    again = run_cli(*command)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "all 4 runs done already" in again.stdout
    assert (out / "results.jsonl").read_bytes() == results   # nothing new was run or written
    assert not (out / "runs" / "seed-1_PAN-100" / "attempt-2").exists()
