"""Re-map many stored products on Dask: `python -m rvs_server.mapping.remap_batch PRODUCT... --workflow FILE
[--workers N | --scheduler ADDRESS] [--out DATA_DIR] [--config-dir DIR]`, which `rvs remap` runs.

Each product is one Dask task (remap.py: the server's own workflow engine on the stored views, no
device, no server), on a LocalCluster here or on the workers of an existing scheduler. Each new
product goes beside its source (or under DATA_DIR/products) and names the source in its manifest.
With workers on other machines, the products, the workflow and DATA_DIR must be at the same paths
there (a shared filesystem). It lives in the server's package, not in clients/: it runs the server's
code, where the clients speak only the protocol.

One line per product as it finishes: `SOURCE -> NEW known K hazardous H (S s)`, or why it failed.
Exit status: 0 every product re-mapped; 1 some failed; 2 nothing could be started.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

EXIT_OK, EXIT_FAILED, EXIT_NOT_STARTED = 0, 1, 2


def remap_task(source: str, workflow: str, data_dir: str | None, config_dir: str | None) -> dict[str, Any]:
    """One product, in a Dask worker."""
    from .remap import remap
    started = time.perf_counter()
    result = remap(source, workflow, data_dir=data_dir, config_dir=config_dir)
    return {**result, "seconds": round(time.perf_counter() - started, 2)}


def say_line(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def run_remap(products: list[Path], workflow: Path, data_dir: Path | None = None, config_dir: Path | None = None,
              workers: int | None = None, scheduler: str | None = None,
              say: Callable[[str], None] = say_line) -> tuple[int, list[dict[str, Any]]]:
    """Every product a task; (exit status, each finished task's result)."""
    from distributed import Client, LocalCluster, as_completed
    cluster = None if scheduler else LocalCluster(n_workers=workers or 1, threads_per_worker=1, processes=True,
                                                  dashboard_address=None)
    client = Client(scheduler) if scheduler else Client(cluster)
    results: list[dict[str, Any]] = []
    failed = 0
    try:
        futures = {client.submit(remap_task, str(p.resolve()), str(workflow.resolve()),
                                 str(data_dir.resolve()) if data_dir else None,
                                 str(config_dir.resolve()) if config_dir else None,
                                 key=f"rvs-remap-{p.name}-{time.time_ns()}", pure=False): p for p in products}
        for future in as_completed(futures):
            source = futures[future]
            if future.status == "finished":
                result = future.result()
                results.append(result)
                say(f"{source.name} -> {result['product']} known {result['known']} hazardous {result['hazardous']} "
                    f"({result['seconds']:.1f} s)")
            else:
                failed += 1
                say(f"{source.name}: FAILED: {future.exception()}")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return (EXIT_OK if failed == 0 else EXIT_FAILED), results


def parser() -> argparse.ArgumentParser:
    parsed = argparse.ArgumentParser(prog="rvs remap", description="re-run a mapping workflow on the views dem-* "
                                     "products stored, on Dask, with no device")
    parsed.add_argument("products", nargs="+", metavar="PRODUCT", help="product folders (data/products/NAME)")
    parsed.add_argument("--workflow", required=True, metavar="FILE", help="the workflow (YAML) to run on them")
    where = parsed.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="worker processes of a LocalCluster on this machine (default: one per product, "
                            "at most the CPU count)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler (tcp://HOST:8786) instead of a LocalCluster")
    parsed.add_argument("--out", default=None, metavar="DATA_DIR",
                        help="write the new products to DATA_DIR/products (default: beside each source)")
    parsed.add_argument("--config-dir", default=None, metavar="DIR",
                        help="take the mapping settings ($config) from DIR/mapping.toml instead of the source's")
    return parsed


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)

    def warn(message: str) -> int:
        sys.stderr.write(f"rvs: {message}\n")
        return EXIT_NOT_STARTED

    products = [Path(p) for p in args.products]
    missing = [str(p) for p in products if not (p / "product.json").is_file()]
    if missing:
        return warn(f"not a product folder (no product.json): {', '.join(missing)}")
    workflow = Path(args.workflow)
    if not workflow.is_file():
        return warn(f"--workflow {workflow}: no such file")
    if args.workers is not None and args.workers < 1:
        return warn("--workers must be 1 or more")
    try:
        import distributed  # noqa: F401
    except ImportError:
        return warn("rvs remap needs Dask: pip install -e '.[cluster]'")
    workers = args.workers or (None if args.scheduler else max(1, min(len(products), os.cpu_count() or 1)))
    status, _ = run_remap(products, workflow, Path(args.out) if args.out else None,
                          Path(args.config_dir) if args.config_dir else None, workers, args.scheduler)
    return status


if __name__ == "__main__":
    sys.exit(main())
