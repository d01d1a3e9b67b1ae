"""Code health in the suite: ruff's lint (with the import order) over all our code, and mypy's types over
the server's core and the toolbox, as configured in pyproject.toml. A finding fails the test with the
tool's own report, so .ci/run catches it on every submission.

By hand, from the repository:

    .venv/bin/ruff check rvs_server toolbox drivers clients tests
    .venv/bin/mypy
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINTED = ["rvs_server", "toolbox", "drivers", "clients", "tests"]


def run_tool(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def test_ruff_finds_nothing():
    result = run_tool("ruff", "check", "--no-cache", "--output-format", "full", *LINTED, timeout=120)
    assert result.returncode == 0, f"ruff check {' '.join(LINTED)}:\n{result.stdout}{result.stderr}"


def test_mypy_finds_nothing():
    """The files, the strictness and the libraries read as untyped are pyproject.toml's [tool.mypy]."""
    result = run_tool("mypy", "--no-incremental", "--no-error-summary", "--show-error-codes", timeout=900)
    assert result.returncode == 0, f"mypy (pyproject.toml [tool.mypy]):\n{result.stdout}{result.stderr}"
