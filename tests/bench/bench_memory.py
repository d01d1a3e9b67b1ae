"""Memory of a real rvs-server on the default world: idle, and at the peak of a full 360 degree dem-full-tof.

    .venv/bin/python tests/bench/bench_memory.py [--world-config configs/world.toml] [--no-dem]

Each figure is printed beside its reference, measured in the same run:
- idle: the server's resident memory once the world is built (a move-ptu job waits for the build)
  and the job has ended, beside the same server on a world of 2 m across (the libraries, the
  transports and the devices without the world's bulk): the difference is what the world holds;
- dem-full-tof: the server's high-water mark (VmHWM) over the whole job, beside idle.
Goals (issue 26): idle under 400 MiB, dem-full-tof peak under 1536 MiB, the world included.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from conftest import REPO, ServerProcess  # noqa: E402

TINY_WORLD = "seed = 1\nsize_m = [2.0, 2.0]\n[rocks]\ncover = 0.0\nclear_radius_m = 0.0\n[craters]\ncount = 0\n"


def memory_mib(pid: int) -> dict[str, float]:
    """VmRSS (now), VmHWM (the high-water mark) and RssAnon (not backed by a file) in MiB."""
    found = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM", "RssAnon", "RssFile"):
            found[key] = int(value.split()[0]) / 1024
    return found


def children(pid: int) -> list[int]:
    """The server's child processes (the native worker runs the heavy steps of jobs in one)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(child) for child in (task / "children").read_text().split()]
    return found


def configs(base: Path, world: str | None) -> Path:
    config_dir = base / "configs"
    shutil.copytree(REPO / "configs", config_dir)
    shutil.copytree(REPO / "workflows", base / "workflows")
    if world is not None:
        (config_dir / "world.toml").write_text(world)
    return config_dir


def started(base: Path, world: str | None) -> ServerProcess:
    server = ServerProcess(data_dir=base / "data", config_dir=configs(base, world))
    server.start(timeout=180)
    with server.connect(timeout=300) as client:       # waits for the world's build, then moves the PTU
        reply = client.command("move-ptu --pan 0 --tilt 0", timeout=300)
    assert " OK " in reply, reply
    time.sleep(1.0)
    return server


def idle(base: Path, world: str | None) -> tuple[ServerProcess, dict[str, float]]:
    server = started(base, world)
    return server, memory_mib(server.proc.pid)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world-config", type=Path, default=REPO / "configs" / "world.toml")
    parser.add_argument("--no-dem", action="store_true", help="measure idle only")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tiny, tiny_memory = idle(Path(tmp) / "tiny", TINY_WORLD)
        tiny.stop()
        server, idle_memory = idle(Path(tmp) / "default", args.world_config.read_text())
        try:
            rss, tiny_rss = idle_memory["VmRSS"], tiny_memory["VmRSS"]
            print(f"idle server, default world: RSS {rss:.0f} MiB (anonymous {idle_memory['RssAnon']:.0f}, file "
                  f"{idle_memory['RssFile']:.0f}); on a 2 m world {tiny_rss:.0f} MiB: the world holds "
                  f"{rss - tiny_rss:.0f} MiB; ratio {rss / tiny_rss:.2f}; goal under 400 MiB")
            if not args.no_dem:
                begun = time.perf_counter()
                with server.connect(timeout=60) as client:
                    reply = client.command("dem-full-tof", timeout=1800)
                assert " OK " in reply, reply
                after = memory_mib(server.proc.pid)
                workers = [memory_mib(child)["VmHWM"] for child in children(server.proc.pid)]
                both = after["VmHWM"] + sum(workers)
                print(f"dem-full-tof ({time.perf_counter() - begun:.0f} s): peak RSS {after['VmHWM']:.0f} MiB in the "
                      f"server, {' + '.join(f'{w:.0f}' for w in workers) or 'no'} MiB in its worker, {both:.0f} MiB "
                      f"together; after it {after['VmRSS']:.0f} MiB; idle {idle_memory['VmRSS']:.0f} MiB; ratio "
                      f"{both / idle_memory['VmRSS']:.2f}; goal under 1536 MiB")
        finally:
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
