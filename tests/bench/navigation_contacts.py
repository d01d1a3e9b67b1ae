"""How hard the rover touched what it touched: for each run of measure_navigation.py, the path
samples (every 5 cm) whose footprint covers a true rock, by the rock's height above the ground.

    .venv/bin/python tests/bench/navigation_contacts.py [--out /tmp/rvs-navigation]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from drivers.sim.config import WorldConfig  # noqa: E402
from drivers.sim.rover import Rover  # noqa: E402
from drivers.sim.world import World  # noqa: E402

LEVELS = (0.10, 0.15, 0.20)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-navigation"))
    args = parser.parse_args()
    runs = [json.loads(line) for line in (args.out / "results.jsonl").read_text().splitlines()]
    worlds: dict[int, World] = {}
    table = {sensor: {level: [] for level in LEVELS} for sensor in ("tof", "stereo")}
    for run in sorted(runs, key=lambda r: (r["seed"], r["sensor"])):
        if run["contacts"] == 0:
            for level in LEVELS:
                table[run["sensor"]][level].append(0)
            continue
        seed = run["seed"]
        if seed not in worlds:
            worlds.clear()
            config = (args.out / f"scene{seed}-{run['sensor']}" / "configs" / "world.toml").read_text()
            import tomllib
            worlds[seed] = World.build(WorldConfig(**tomllib.loads(config)))
        rover = Rover(worlds[seed])
        truth = json.loads((Path(run["product"]) / "truth" / "traverse.json").read_text())
        heights = []
        for x, y, heading in truth["path"]:
            rover.place(x, y, heading)
            heights.append(float(rover.footprint_protrusion().max(initial=0.0)))
        heights = np.array(heights)
        for level in LEVELS:
            table[run["sensor"]][level].append(int(np.sum(heights > level)))
        print(f"scene {seed} {run['sensor']}: samples over a rock > 10 / 15 / 20 cm: "
              f"{[int(np.sum(heights > level)) for level in LEVELS]}, tallest {heights.max():.3f} m", flush=True)
    for sensor, counts in table.items():
        runs_n = len(counts[LEVELS[0]])
        if runs_n:
            parts = [f"> {int(level * 100)} cm: {sum(1 for c in counts[level] if c)} runs, "
                     f"{sum(counts[level])} samples" for level in LEVELS]
            print(f"{sensor} ({runs_n} runs; a sample is 5 cm of path or up to 10 degrees of turn): "
                  + "; ".join(parts))


if __name__ == "__main__":
    main()
