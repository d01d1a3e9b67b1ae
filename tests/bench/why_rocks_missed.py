"""Why the maps miss rocks (issue 27 item 1): each true obstacle a product saw but did not call a hazard,
put in one class from the product's own files.

    .venv/bin/python tests/bench/why_rocks_missed.py PRODUCT_DIR... [--within 4.0]

A product re-mapped onto another grid (`rvs remap` copies the truth only where the grid is the same)
takes its truth from the source its product.json names, placed onto its own grid.

A rock is a connected patch of truth/obstacles.tif (protruding over the step threshold, 0.1 m); it is
seen when a known DEM cell lies on it and missed when no hazard cell lies on it or next to it (the
rule maps_scoring.score_product counts recall by). Each missed rock, in the first class that fits:
- filled: every known cell on it was filled across a hole (counts 0), no point measured it;
- edge: measured by fewer than 3 points in all (seen at the edge of a view, or past a crest);
- read low: its highest measured cell stands more than 3 cm below its true top (a shadowed or
  mismatched top, a face seen from the side);
- step under: its top is measured but the step the map computed there stays below the limit (the
  ground around it is unseen or read high, or the rock barely passes the limit);
- other.
Printed per rock: range from the rover, true protrusion over the ground round it, the map's step and
how far the measured top reads below the truth; then the counts per class.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from rvs_server.products.rasters import read_geotiff  # noqa: E402
from toolbox.mapping.dem import _overlap_slices  # noqa: E402

STEP_LIMIT = 0.10
READ_LOW_M = 0.03
EDGE_POINTS = 3
RING_M = 0.3       # the ground round a rock: this far beyond its outline


def truth_of(product: Path) -> Path:
    """The product's truth/ folder, or its source's (a remap onto another grid copies none)."""
    if (product / "truth" / "height.tif").exists():
        return product / "truth"
    source = json.loads((product / "product.json").read_text()).get("source", {})
    path = Path(source.get("path", "")) if isinstance(source, dict) else Path(str(source))
    if not (path / "truth" / "height.tif").exists():
        raise FileNotFoundError(f"{product}: no truth/ and no source product with one (product.json source)")
    return path / "truth"


def on_grid(path: Path, spec) -> np.ndarray:
    """A truth grid placed onto `spec` (cell-aligned grids; NaN where it does not reach)."""
    values, source = read_geotiff(path)
    out = np.full(spec.shape, np.nan, dtype=np.float32)
    target, inside = _overlap_slices(source, spec)
    if target is not None:
        out[target] = values[inside]
    return out


def missed_rocks(product: Path, within: float) -> list[dict]:
    dem, spec = read_geotiff(product / "dem.tif")
    counts = read_geotiff(product / "counts.tif")[0]
    step = read_geotiff(product / "step.tif")[0]
    code = read_geotiff(product / "hazard.tif")[0]
    truth_dir = truth_of(product)
    truth = on_grid(truth_dir / "height.tif", spec)
    obstacles = on_grid(truth_dir / "obstacles.tif", spec) > 0.5
    rover = json.loads((truth_dir / "state.json").read_text())["rover"]
    known = np.isfinite(dem)
    hazard = known & (code != 255) & (code.astype(np.int64) % 2 == 1)
    near_hazard = ndimage.binary_dilation(hazard, iterations=1)
    xs, ys = spec.centres()
    distance = np.hypot(xs[None, :] - rover["x"], ys[:, None] - rover["y"])
    labels, count = ndimage.label(obstacles)
    ring_cells = max(1, int(round(RING_M / spec.cell)))
    found = []
    for index in range(1, count + 1):
        rock = labels == index
        if not (rock & known).any() or (rock & near_hazard).any():
            continue
        range_m = float(distance[rock].min())
        if range_m > within:
            continue
        ring = ndimage.binary_dilation(rock, iterations=ring_cells) & ~ndimage.binary_dilation(rock, iterations=1)
        ground = float(np.nanmedian(truth[ring])) if ring.any() else float("nan")
        measured = rock & known & (counts > 0)
        top_true = float(np.nanmax(truth[rock]))
        top_read = float(np.nanmax(dem[measured])) if measured.any() else float("nan")
        points = int(counts[rock & known].sum())
        step_max = float(np.nanmax(np.where(rock & known, step, np.nan))) if (rock & known).any() else float("nan")
        if not measured.any():
            why = "filled"
        elif points < EDGE_POINTS:
            why = "edge"
        elif top_true - top_read > READ_LOW_M:
            why = "read low"
        elif not step_max > STEP_LIMIT:
            why = "step under"
        else:
            why = "other"
        ring_known = float((ring & known).mean() / max(ring.mean(), 1e-12)) if ring.any() else 0.0
        found.append({"product": product.name, "range_m": range_m, "protrusion_m": top_true - ground,
                      "step_m": step_max, "read_low_m": top_true - top_read, "points": points,
                      "cells": int(rock.sum()), "ground_seen": ring_known, "why": why})
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("products", type=Path, nargs="+")
    parser.add_argument("--within", type=float, default=4.0, help="only rocks this near the rover, metres")
    args = parser.parse_args()
    rows = [row for product in args.products for row in missed_rocks(product, args.within)]
    for row in rows:
        print(f"{row['product'][:40]:40s} {row['why']:10s} range {row['range_m']:4.2f} m  protrusion "
              f"{100 * row['protrusion_m']:5.1f} cm  step {100 * row['step_m']:5.1f} cm  top reads "
              f"{100 * row['read_low_m']:+5.1f} cm low  points {row['points']:4d} on {row['cells']:3d} cells  "
              f"ground round it seen {row['ground_seen']:.2f}")
    print(f"missed within {args.within:g} m: {len(rows)}; " +
          ", ".join(f"{why} {n}" for why, n in Counter(r["why"] for r in rows).most_common()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
