"""Build a simulated world and save it, for `rvs-server --world FILE`.

    .venv/bin/python -m drivers.sim save FILE [--config configs/world.toml] [--seed N]
"""
from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

from .config import WorldConfig
from .world import World


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m drivers.sim")
    sub = parser.add_subparsers(dest="action", required=True)
    save = sub.add_parser("save", help="build a world and save it to FILE (.npz)")
    save.add_argument("file")
    save.add_argument("--config", default="configs/world.toml", help="world configuration (TOML)")
    save.add_argument("--seed", type=int, help="override the configuration's seed")
    args = parser.parse_args(argv)
    data = tomllib.loads(Path(args.config).read_text()) if Path(args.config).exists() else {}
    if args.seed is not None:
        data["seed"] = args.seed
    started = time.perf_counter()
    world = World.build(WorldConfig.model_validate(data))
    path = world.save(args.file)
    print(f"saved seed {world.config.seed} world to {path} in {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
