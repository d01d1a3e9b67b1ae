"""`rvs remap PRODUCT... --workflow FILE [--workers N | --scheduler ADDRESS] [--out DATA_DIR] [--config-dir DIR]`

Re-runs a mapping workflow on the views that dem-* products stored, with no device and no server, each
product a Dask task. The work is the server's own workflow engine (rvs_server/mapping/remap_batch.py),
so `rvs` runs it as a process of its own (`python -m rvs_server.mapping.remap_batch ...`): the clients
import nothing of the server but its protocol. Its lines and exit status are the command's.
"""
from __future__ import annotations

import argparse
import subprocess
import sys

BATCH = "rvs_server.mapping.remap_batch"


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("remap", help="re-run a mapping workflow on stored views, on Dask (no devices)",
                                 add_help=False)
    parser.add_argument("arguments", nargs=argparse.REMAINDER,
                        help=f"PRODUCT... --workflow FILE [...]: see `python -m {BATCH} --help`")


def command_remap(args: argparse.Namespace) -> int:
    return subprocess.run([sys.executable, "-m", BATCH, *args.arguments], stdin=subprocess.DEVNULL).returncode
