"""How `rvs campaign` scales on Dask: the navigation campaign's TOF scenes (orient off) three ways.

- `local-1`: a LocalCluster of one worker;
- `local-2`: a LocalCluster of two workers;
- `scheduler-2`: a `dask scheduler` and two `dask worker` commands, separate processes on loopback
  (what two machines would run, one worker each).

Each mode runs the same runs of tests/bench/campaigns/navigation.toml into an empty folder of its own
and is timed from submission to the last result; its wall time, the runs' own times and what they
scored are appended to --results the moment the mode ends, and a rerun skips the modes already there
(same scenes), so the three modes may be run in separate sessions. The figure is each mode's wall
time over local-1's of the same file: measured on the same machine, if not in the same run.

    .venv/bin/python tests/bench/bench_campaign_scaling.py [--scenes 10] [--modes local-1 local-2 scheduler-2]
        [--out /tmp/rvs-scaling] [--results tests/bench/results/campaign-scaling.jsonl]
    .venv/bin/python tests/bench/bench_campaign_scaling.py --report tests/bench/results/campaign-scaling.jsonl
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from clients.campaign import Campaign, load_campaign, run_campaign  # noqa: E402
from clients.run_log import RunLog, read_runs  # noqa: E402

RESULTS = REPO / "tests" / "bench" / "results" / "campaign-scaling.jsonl"
CAMPAIGN = REPO / "tests" / "bench" / "campaigns" / "navigation.toml"
MODES = ("local-1", "local-2", "scheduler-2")
BIN = Path(sys.executable).parent


def tof_runs(scenes: int) -> Campaign:
    """navigation.toml's runs of the first `scenes` scenes, TOF with orient off."""
    campaign = load_campaign(CAMPAIGN)
    chosen = [run for run in campaign.runs if run["SENSOR"] == "tof" and run["ORIENT"] == "off"]
    seeds = sorted({run["seed"] for run in chosen})[:scenes]
    return dataclasses.replace(campaign, runs=[run for run in chosen if run["seed"] in seeds])


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextmanager
def loopback_cluster(workers: int, folder: Path):
    """A `dask scheduler` and `workers` `dask worker` commands on loopback, each a process of its own
    with its log in `folder`; yields the scheduler's address once every worker has joined."""
    from distributed import Client
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    folder.mkdir(parents=True, exist_ok=True)
    processes = []
    try:
        processes.append(subprocess.Popen(
            [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
            stdout=open(folder / "scheduler.log", "w"), stderr=subprocess.STDOUT))
        for index in range(workers):
            processes.append(subprocess.Popen(
                [str(BIN / "dask"), "worker", address, "--nthreads", "1", "--nworkers", "1",
                 "--resources", "servers=1", "--name", f"worker-{index}", "--no-dashboard"],
                stdout=open(folder / f"worker-{index}.log", "w"), stderr=subprocess.STDOUT, cwd=REPO))
        deadline = time.monotonic() + 120
        while True:
            try:
                with Client(address, timeout=5) as client:
                    client.wait_for_workers(workers, timeout=max(1.0, deadline - time.monotonic()))
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(1.0)
        yield address
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()


def run_mode(campaign: Campaign, mode: str, out: Path) -> dict[str, Any]:
    """One mode's campaign into an empty folder: its wall time and its runs' results."""
    folder = out / mode
    shutil.rmtree(folder, ignore_errors=True)
    started = time.monotonic()
    if mode.startswith("local-"):
        code = run_campaign(campaign, folder, workers=int(mode.split("-")[1]))
    else:
        with loopback_cluster(int(mode.split("-")[1]), out / f"{mode}-cluster") as address:
            started = time.monotonic()   # the cluster's start is not the campaign's
            code = run_campaign(campaign, folder, scheduler=address)
    wall = time.monotonic() - started
    runs = RunLog(folder / "results.jsonl", campaign.settings).runs()
    finished = [r for r in runs if "error" not in r]
    values = [r.get("values", {}) for r in finished]
    return {"wall_s": round(wall, 1), "exit": code, "runs": len(campaign.runs), "finished": len(finished),
            "failed": len(runs) - len(finished), "run_seconds": round(sum(r["seconds"] for r in finished), 1),
            "arrived": sum(bool(v.get("success")) for v in values),
            "contacts": sum(int(v.get("contacts", 0)) for v in values),
            "hosts": sorted({str(r.get("host")) for r in finished}),
            "localisation_m": sorted(float(v["localisation_error_m"]) for v in values if "localisation_error_m" in v)}


def report(path: Path) -> str:
    records = read_runs(path)
    if not records:
        return f"{path}: no modes"
    lines = []
    for scenes in sorted({r["run"]["scenes"] for r in records}):
        chosen = {r["run"]["mode"]: r for r in records if r["run"]["scenes"] == scenes}
        one = chosen.get("local-1")
        lines += [f"== {scenes} TOF navigation scenes, orient off",
                  "| mode | wall | ratio to one worker | arrived | contacts | sum of the runs' own times |",
                  "|---|---|---|---|---|---|"]
        for mode in [m for m in MODES if m in chosen]:
            r = chosen[mode]
            ratio = f"{one['wall_s'] / r['wall_s']:.2f}" if one else "-"
            lines.append(f"| {mode} | {r['wall_s']:.1f} s | {ratio} | {r['arrived']}/{r['finished']} | "
                         f"{r['contacts']} | {r['run_seconds']:.0f} s |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-scaling"))
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--report", type=Path, metavar="FILE", help="print the table of a results file and stop")
    args = parser.parse_args()
    if args.report:
        print(report(args.report))
        return
    campaign = tof_runs(args.scenes)
    log = RunLog(args.results, {"campaign": "navigation.toml", "sensor": "tof", "orient": "off"})
    for mode in args.modes:
        key = {"mode": mode, "scenes": args.scenes}
        if RunLog.key(key) in log.done():
            print(f"{mode}: already in {args.results}", flush=True)
            continue
        print(f"{mode}: {len(campaign.runs)} runs ...", flush=True)
        measured = run_mode(campaign, mode, args.out)
        log.append(key, measured["wall_s"], **measured)
        print(f"{mode}: {json.dumps(measured)}", flush=True)
    print(report(args.results))


if __name__ == "__main__":
    main()
