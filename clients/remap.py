"""`rvs remap PRODUCT... --workflow FILE [--workers N | --scheduler ADDRESS] [--out DATA_DIR]`

Re-runs a mapping workflow on the views that dem-* products stored, with no device and no server:
each product is one Dask task (rvs_server/mapping/remap.py), on a LocalCluster here or on the
workers of an existing scheduler. Each new product goes beside its source (or under DATA_DIR/products)
and names the source in its manifest. With workers on other machines, the products, the workflow and
DATA_DIR must be at the same paths there (a shared filesystem).

One line per product as it finishes: `SOURCE -> NEW known K hazardous H (S s)`, or why it failed.
Exit status: 0 every product re-mapped; 1 some failed; 2 nothing could be started.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

EXIT_OK, EXIT_FAILED, EXIT_NOT_STARTED = 0, 1, 2


def remap_task(source: str, workflow: str, data_dir: str | None, config_dir: str | None) -> dict[str, Any]:
    """One product, in a Dask worker."""
    from rvs_server.mapping.remap import remap
    started = time.perf_counter()
    result = remap(source, workflow, data_dir=data_dir, config_dir=config_dir)
    return {**result, "seconds": round(time.perf_counter() - started, 2)}


def run_remap(products: list[Path], workflow: Path, data_dir: Path | None = None, config_dir: Path | None = None,
              workers: int | None = None, scheduler: str | None = None,
              say: Callable[[str], None] = print) -> tuple[int, list[dict[str, Any]]]:
    """Every product a task; (exit status, each finished task's result)."""
    from distributed import as_completed

    from .campaign import _open_client
    client, cluster = _open_client(workers, scheduler)
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


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("remap", help="re-run a mapping workflow on stored views, on Dask (no devices)")
    parser.add_argument("products", nargs="+", metavar="PRODUCT", help="product folders (data/products/NAME)")
    parser.add_argument("--workflow", required=True, metavar="FILE", help="the workflow (YAML) to run on them")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="worker processes of a LocalCluster on this machine (default: one per product, "
                            "at most the CPU count)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler (tcp://HOST:8786) instead of a LocalCluster")
    parser.add_argument("--out", default=None, metavar="DATA_DIR",
                        help="write the new products to DATA_DIR/products (default: beside each source)")
    parser.add_argument("--config-dir", default=None, metavar="DIR",
                        help="take the mapping settings ($config) from DIR/mapping.toml instead of the source's")


def command_remap(args: argparse.Namespace) -> int:
    def warn(message: str) -> None:
        print(f"rvs: {message}", file=sys.stderr, flush=True)

    products = [Path(p) for p in args.products]
    missing = [str(p) for p in products if not (p / "product.json").is_file()]
    if missing:
        warn(f"not a product folder (no product.json): {', '.join(missing)}")
        return EXIT_NOT_STARTED
    workflow = Path(args.workflow)
    if not workflow.is_file():
        warn(f"--workflow {workflow}: no such file")
        return EXIT_NOT_STARTED
    if args.workers is not None and args.workers < 1:
        warn("--workers must be 1 or more")
        return EXIT_NOT_STARTED
    try:
        import distributed  # noqa: F401
    except ImportError:
        warn("rvs remap needs Dask: pip install -e '.[cluster]'")
        return EXIT_NOT_STARTED
    workers = args.workers or (None if args.scheduler else max(1, min(len(products), os.cpu_count() or 1)))
    status, _ = run_remap(products, workflow, Path(args.out) if args.out else None,
                          Path(args.config_dir) if args.config_dir else None, workers, args.scheduler)
    return status
