"""The maps campaign: a full TOF panorama and a full stereo panorama on the default world, per seed,
each product scored against the simulator's truth from its own files only (the maps beside the
truth/ grids, as anyone could score it without our code):

- DEM height error over observed cells: RMSE, 95th percentile of |error|, mean (bias);
- share of the panorama's area observed: known cells within the sensor's reach of the rover;
- hazard recall: true obstacles (connected rocks protruding more than the step threshold) that
  were observed and have a hazard cell on them;
- false hazards: the share of truly safe observed cells (no obstacle within 0.1 m) marked hazardous.
Also dem-full-tof's time per step and the server's peak memory.

Used by tests/bench/campaigns/maps.toml (`rvs campaign`: its hooks name this file) and by
tests/bench/measure_maps.py: the same scores and lines from the same code.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from rvs_server.products.rasters import read_geotiff

REACH_M = {"tof": 4.5, "stereo": 4.5, "fused": 4.5}  # the same disc for all, inside both sensors' range
NEAR_M = 4.0      # the map-quality goals (issue 27) are stated within 4 m of the rover
SENSORS = ("tof", "stereo")
KEYS = ("rmse", "p95", "bias", "observed", "recall", "rocks", "false_hazard")
NEAR_KEYS = ("rmse_4m", "bias_4m", "recall_4m", "rocks_4m", "false_hazard_4m")


def score_product(product: Path, sensor: str) -> dict[str, float]:
    """Every score of one dem-full(-tof) product against its truth/ grids."""
    dem, spec = read_geotiff(product / "dem.tif")
    truth, _ = read_geotiff(product / "truth" / "height.tif")
    code, _ = read_geotiff(product / "hazard.tif")
    obstacles = read_geotiff(product / "truth" / "obstacles.tif")[0] > 0.5
    state = json.loads((product / "truth" / "state.json").read_text())
    known = np.isfinite(dem)
    error = (dem - truth)[known]
    hazard = known & (code != 255) & (code.astype(np.int64) % 2 == 1)
    xs, ys = spec.centres()
    distance = np.hypot(xs[None, :] - state["rover"]["x"], ys[:, None] - state["rover"]["y"])
    reach = distance <= REACH_M[sensor]
    labels, count = ndimage.label(obstacles)
    seen = detected = seen_near = detected_near = 0
    near_hazard = ndimage.binary_dilation(hazard, iterations=1)
    for index in range(1, count + 1):
        rock = labels == index
        if (rock & known).any():
            found = bool((rock & near_hazard).any())
            seen, detected = seen + 1, detected + found
            if float(np.mean(distance[rock])) <= NEAR_M:      # a rock within 4 m by its centre
                seen_near, detected_near = seen_near + 1, detected_near + found
    safe = known & ~ndimage.binary_dilation(obstacles, iterations=max(1, int(round(0.1 / spec.cell))))
    near = distance <= NEAR_M
    error_near = (dem - truth)[known & near]
    return {"rmse": float(np.sqrt(np.mean(error ** 2))), "p95": float(np.percentile(np.abs(error), 95)),
            "bias": float(error.mean()), "observed": float(known[reach].mean()),
            "recall": detected / max(seen, 1), "rocks": seen,
            "false_hazard": float(hazard[safe].sum() / max(safe.sum(), 1)),
            "rmse_4m": float(np.sqrt(np.mean(error_near ** 2))), "bias_4m": float(error_near.mean()),
            "recall_4m": detected_near / max(seen_near, 1), "rocks_4m": seen_near,
            "false_hazard_4m": float(hazard[safe & near].sum() / max((safe & near).sum(), 1))}


def timings(product: Path) -> dict[str, float]:
    """The product's time per step (product.json timings_s)."""
    return dict(json.loads((product / "product.json").read_text())["timings_s"])


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def seed_line(seed: int, sensor: str, result: dict[str, Any]) -> str:
    return (f"seed {seed} {sensor:6s} rmse {result['rmse'] * 100:5.2f} cm  "
            f"p95 {result['p95'] * 100:5.2f} cm  "
            f"bias {result['bias'] * 100:+5.2f} cm  observed {result['observed']:.2f}  "
            f"recall {result['recall']:.2f} ({result['rocks']} rocks)  "
            f"false hazard {result['false_hazard']:.3f}")


def near_line(seed: int, sensor: str, result: dict[str, Any]) -> str:
    return (f"seed {seed} {sensor:6s} within {NEAR_M:g} m: rmse {result['rmse_4m'] * 100:5.2f} cm  "
            f"bias {result['bias_4m'] * 100:+5.2f} cm  recall {result['recall_4m']:.2f} ({result['rocks_4m']} rocks)  "
            f"false hazard {result['false_hazard_4m']:.3f}")


def summarise(records: list[dict[str, Any]], sensor: str) -> str:
    """One sensor's seeds of a results file (clients/run_log.report): a line per seed and the mean."""
    rows = sorted((r for r in records if r["sensor"] == sensor), key=lambda r: r["seed"])
    if not rows:
        return ""
    lines = [seed_line(r["seed"], sensor, r) + "\n" + near_line(r["seed"], sensor, r) for r in rows]
    mean = {key: float(np.mean([r[key] for r in rows])) for key in NEAR_KEYS}
    lines.append(mean_line(sensor, [{key: r[key] for key in KEYS} for r in rows]) + f" ({len(rows)} seeds)")
    lines.append(f"mean {sensor:6s} within {NEAR_M:g} m: rmse {mean['rmse_4m'] * 100:5.2f} cm  bias "
                 f"{mean['bias_4m'] * 100:+5.2f} cm  recall {mean['recall_4m']:.2f} "
                 f"({sum(r['rocks_4m'] for r in rows)} rocks)  false hazard {mean['false_hazard_4m']:.3f}")
    return "\n".join(lines)


def timing_line(seed: int, steps: dict[str, float], peak: float) -> str:
    return (f"seed {seed} dem-full-tof seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in steps.items())
            + f"; server peak memory {peak:.0f} MiB (world included)")


def mean_line(sensor: str, results: list[dict[str, Any]]) -> str:
    mean = {key: np.mean([r[key] for r in results]) for key in results[0]}
    return (f"mean {sensor:6s} rmse {mean['rmse'] * 100:5.2f} cm  p95 {mean['p95'] * 100:5.2f} cm  bias "
            f"{mean['bias'] * 100:+5.2f} cm  observed {mean['observed']:.2f}  recall {mean['recall']:.2f}  "
            f"false hazard {mean['false_hazard']:.3f}")


# -- the campaign file's hooks (tests/bench/campaigns/maps.toml) -------------------------------------------


def runs(seeds: list[int] | None = None) -> list[dict[str, Any]]:
    """One run per seed of the default world (configs/world.toml with --world-seed)."""
    return [{"seed": int(seed)} for seed in (seeds if seeds is not None else [1, 2, 3, 4, 5])]


def score(run: dict[str, Any], data_dir: Path, pid: int | None = None) -> dict[str, Any]:
    """Both panoramas' scores (tof_rmse, stereo_rmse, ...), dem-full-tof's timings and the peak memory of
    the server (`pid`: the engine hands it over while the server still runs; nan without it); the
    products are the mission's `--output tof` and `--output stereo`."""
    products = Path(data_dir, "products")
    values: dict[str, Any] = {}
    for sensor in SENSORS:
        values.update({f"{sensor}_{key}": value for key, value in score_product(products / sensor, sensor).items()})
    values["tof_timings_s"] = timings(products / "tof")
    values["peak_memory_mib"] = peak_rss_mib(pid) if pid is not None else float("nan")
    return values


def report(records: list[dict[str, Any]]) -> str:
    """measure_maps.py's lines: per seed and sensor, the timings, then the means per sensor."""
    records = sorted(records, key=lambda record: record["run"]["seed"])
    lines, rows = [], {sensor: [] for sensor in SENSORS}
    for record in records:
        seed, values = record["run"]["seed"], record.get("values", {})
        for sensor in SENSORS:
            result = {key: values[f"{sensor}_{key}"] for key in KEYS}
            rows[sensor].append(result)
            lines.append(seed_line(seed, sensor, result))
        lines.append(timing_line(seed, values["tof_timings_s"], values["peak_memory_mib"]))
    lines += [mean_line(sensor, results) for sensor, results in rows.items() if results]
    return "\n".join(lines)
