"""Accuracy of the maps against the simulated world's truth, TOF, stereo and fused side by side.

For each seed, a real server on the default world (configs/world.toml with --world-seed) runs a full
dem-full-tof panorama and a dem-full panorama (and, with `--sensors ... fused`, a dem-full-fused one);
each product is scored from its own files only (the maps beside the truth/ grids, as anyone could
score it without our code):

- DEM height error over observed cells: RMSE, 95th percentile of |error|, mean (bias);
- share of the panorama's area observed: known cells within the sensor's reach of the rover;
- hazard recall: true obstacles (connected rocks protruding more than the step threshold) that
  were observed and have a hazard cell on them;
- false hazards: the share of truly safe observed cells (no obstacle within 0.1 m) marked hazardous.
Also prints dem-full-tof's time per step and the server's peak memory.

    .venv/bin/python tests/bench/measure_maps.py [--seeds 1 2 3 4 5] [--sim-speed 100]
        [--sensors tof stereo fused] [--label NAME] [--results tests/bench/results/maps.jsonl] [--keep DIR]
    .venv/bin/python tests/bench/measure_maps.py --report tests/bench/results/maps.jsonl

Each seed's scores per sensor, the whole disc's and within 4 m of the rover (the map-quality goals'
reach: rocks counted by their centre), go to --results as the seed ends (clients/run_log.py); a rerun
with the same --label and sim speed skips the seeds and sensors already there. --label names the
code's revision (the maps' rules change; the file keeps one table per label). --keep DIR keeps the
products for why_rocks_missed.py; without it they go with a temporary folder.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from maps_scoring import near_line, peak_rss_mib, score_product, seed_line, summarise, timing_line, timings  # noqa: E402

from clients.run_log import RunLog, add_results_options, report, reported  # noqa: E402

import conftest  # noqa: E402
from conftest import ServerProcess, pairs  # noqa: E402

COMMANDS = {"tof": "dem-full-tof", "stereo": "dem-full", "fused": "dem-full-fused"}
RESULTS = REPO / "tests" / "bench" / "results" / "maps.jsonl"


def run(client, line: str) -> dict[str, str]:
    reply = client.command(line, timeout=1800)
    if reply.split()[1] != "OK":
        raise RuntimeError(f"{line}: {reply}")
    return pairs(reply)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--sim-speed", type=float, default=100.0)
    parser.add_argument("--sensors", nargs="+", choices=list(COMMANDS), default=["tof", "stereo"])
    parser.add_argument("--label", default="main", help="the code's revision: one table per label")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="keep each seed's server folder (products) here")
    add_results_options(parser, RESULTS)
    args = parser.parse_args()
    if reported(args, summarise):
        return
    conftest.SIM_SPEED = args.sim_speed
    log = RunLog(args.results, {"label": args.label, "sim_speed": args.sim_speed})
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for seed in args.seeds:
            todo = [sensor for sensor in args.sensors if RunLog.key({"seed": seed, "sensor": sensor}) not in log.done()]
            if not todo:
                print(f"seed {seed}: {', '.join(args.sensors)} already in {args.results}", flush=True)
                continue
            base = root / f"seed{seed}"
            shutil.rmtree(base, ignore_errors=True)
            config_dir = base / "configs"
            conftest.write_configs(config_dir)
            (config_dir / "world.toml").write_text((REPO / "configs" / "world.toml").read_text())
            server = ServerProcess(data_dir=base / "data", config_dir=config_dir,
                                   extra_args=["--world-seed", str(seed)]).start()
            try:
                with server.connect(timeout=900) as c:
                    replies = {}
                    for sensor in todo:
                        started = time.monotonic()
                        replies[sensor] = (run(c, f"{COMMANDS[sensor]} --output {sensor}"), time.monotonic() - started)
                peak = peak_rss_mib(server.proc.pid)
            finally:
                server.stop()
            for sensor, (reply, seconds) in replies.items():
                result = score_product(Path(reply["path"]), sensor)
                log.append({"seed": seed, "sensor": sensor}, seconds, **result,
                           **({"product": reply["path"]} if args.keep else {}))
                print(seed_line(seed, sensor, result) + "\n" + near_line(seed, sensor, result), flush=True)
            if "tof" in replies:
                print(timing_line(seed, timings(Path(replies["tof"][0]["path"])), peak), flush=True)
    print(report(args.results, summarise))


if __name__ == "__main__":
    main()
