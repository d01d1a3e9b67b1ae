"""What hazard detection keeps: one record per frame (its event and its CSV row), and the product
`hazard-stop` closes: frames.csv, stops.csv and corridor.png (the memory around the rover, the last
frames' corridors and detections, the stops)."""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from rvs_server.files import write_text_atomic
from rvs_server.products.canvas import Canvas
from rvs_server.products.rasters import write_png
from toolbox.colour import categorical, with_key, with_title
from toolbox.geometry import RoverPose, footprint_polygon
from toolbox.mapping import hazard as codes
from toolbox.mapping.corridor import CorridorParams, CorridorView, HazardMemory, Hit


def _number(value: float | None, digits: int = 3) -> str:
    return "none" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


@dataclass
class FrameRecord:
    seq: int
    sim_s: float
    state: str                     # clear | hazard | unknown
    hit: Hit | None
    latency_ms: float
    seen: float                    # share of the swept corridor this frame saw
    points: int
    pose: RoverPose
    pan_deg: float
    tilt_deg: float
    direction: int
    reason: str = ""
    truth: list[float] | None = field(default=None)   # simulated: true x, y, heading (rad)

    def event(self) -> dict[str, Any]:
        """The `* EVENT hazard` fields after seq (PROTOCOL.md)."""
        hit = self.hit
        data: dict[str, Any] = {"state": self.state, "distance": _number(hit.distance if hit else None, 2),
                                "x": _number(hit.x if hit else None), "y": _number(hit.y if hit else None),
                                "latency_ms": _number(self.latency_ms if self.state != "unknown" else None, 1)}
        if self.reason:
            data["reason"] = self.reason
        return data

    def row(self) -> list[Any]:
        hit, truth = self.hit, self.truth or [math.nan] * 3
        return [self.seq, f"{self.sim_s:.3f}", self.state, _number(hit.distance if hit else None),
                _number(hit.x if hit else None), _number(hit.y if hit else None),
                codes_words(hit.cause) if hit else "", f"{self.latency_ms:.2f}", f"{self.seen:.3f}", self.points,
                f"{self.pose.x:.3f}", f"{self.pose.y:.3f}", f"{math.degrees(self.pose.heading):.2f}",
                _number(self.pan_deg, 2), _number(self.tilt_deg, 2), self.direction,
                _number(truth[0]), _number(truth[1]), _number(math.degrees(truth[2]) if truth[2] == truth[2] else None, 2),
                self.reason]


FRAME_COLUMNS = ["seq", "sim_s", "state", "distance_m", "x", "y", "cause", "latency_ms", "seen", "points",
                 "est_x", "est_y", "est_heading_deg", "pan_deg", "tilt_deg", "direction",
                 "true_x", "true_y", "true_heading_deg", "reason"]
STOP_COLUMNS = ["seq", "sim_s", "est_x", "est_y", "est_heading_deg", "true_x", "true_y", "true_heading_deg",
                "true_clearance_m", "contacts_so_far", "reason"]


def codes_words(code: int) -> str:
    words = [name for bit, name in ((codes.SLOPE, "slope"), (codes.STEP, "step"), (codes.ROUGHNESS, "roughness"))
             if code & bit]
    return "+".join(words)


def _csv(header: list[str], rows: list[list[Any]]) -> str:
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return text.getvalue()


def stop_row(stop: dict) -> list[Any]:
    truth = stop.get("truth") or {}
    heading = truth.get("heading_rad")
    return [stop["seq"], f"{stop['sim_s']:.3f}", f"{stop['x']:.3f}", f"{stop['y']:.3f}", f"{stop['heading_deg']:.2f}",
            _number(truth.get("x")), _number(truth.get("y")),
            _number(math.degrees(heading) if heading is not None else None, 2),
            _number(truth.get("clearance_m")), truth.get("contacts", ""), stop["reason"]]


def write_product(product: Any, records: list[FrameRecord], stops: list[dict], views: list[CorridorView],
                  memory: HazardMemory, params: CorridorParams, settings: Any, sensor: str) -> None:
    write_text_atomic(product.add("frames.csv", "one row per frame: state, nearest hazard in the path (distance "
                                  "from the leading edge, world x y, cause), latency, the estimate and (simulated) "
                                  "the true pose"), _csv(FRAME_COLUMNS, [r.row() for r in records]))
    write_text_atomic(product.add("stops.csv", "every drive the guard stopped: where, why and (simulated) the "
                                  "true pose and free way left to the nearest true obstacle"),
                      _csv(STOP_COLUMNS, [stop_row(s) for s in stops]))
    picture = corridor_picture(records, stops, views, memory, params, sensor)
    if picture is not None:
        write_png(product.add("corridor.png", "the hazard memory around the rover (north up): the last frames' "
                              "corridors, detections and stops"), picture)
    measured = [r.latency_ms for r in records if r.state != "unknown"]
    product.note("summary", {
        "sensor": sensor, "frames": len(records), "stops": len(stops),
        "states": {s: sum(1 for r in records if r.state == s) for s in ("clear", "hazard", "unknown")},
        "latency_ms": {"p50": float(np.percentile(measured, 50)), "p95": float(np.percentile(measured, 95))}
        if measured else None,
        "corridor": {"reach_m": params.reach, "half_width_m": params.half_width, "cell_m": params.cell},
        "settings": settings.model_dump(mode="json")})
    product.finish()


PALETTE = {codes.SAFE: (70, 110, 70), codes.UNKNOWN: (25, 25, 25)}
HAZARD_RGB = (220, 50, 40)


def corridor_picture(records: list[FrameRecord], stops: list[dict], views: list[CorridorView],
                     memory: HazardMemory, params: CorridorParams, sensor: str) -> np.ndarray | None:
    """North-up picture of the memory: safe green, hazard red, unknown dark; the last frames'
    corridors outlined, their nearest hazards ringed, the rover's estimated path, the stops."""
    spec = memory.spec
    if spec is None:
        return None
    code = memory.code
    rgb = categorical(np.where(codes.is_hazard(code), 1, code), {**PALETTE, 1: HAZARD_RGB})
    rows, cols = np.nonzero(code != codes.UNKNOWN)
    if len(rows):   # crop to what was seen, with a margin
        pad = int(round(1.0 / spec.cell))
        r0, r1 = max(0, rows.min() - pad), min(spec.rows, rows.max() + pad + 1)
        c0, c1 = max(0, cols.min() - pad), min(spec.cols, cols.max() + pad + 1)
        rgb = rgb[r0:r1, c0:c1]
        spec = type(spec)(spec.origin_x + c0 * spec.cell, spec.origin_y + r0 * spec.cell, spec.cell, r1 - r0, c1 - c0)
    canvas = Canvas(rgb, spec, 720)
    path = [(r.pose.x, r.pose.y) for r in records]
    canvas.line(path, (240, 240, 240), 1)
    for view in views:
        x0, y0, heading = view.pose
        outline = footprint_polygon(RoverPose(x0 + math.cos(heading) * params.reach / 2,
                                              y0 + math.sin(heading) * params.reach / 2, 0.0, heading),
                                    params.body_length + params.reach, 2 * params.half_width)
        cv2.polylines(canvas.image, [canvas.pixels(outline)], True, (90, 160, 230), 1, cv2.LINE_AA)
        if view.nearest is not None:
            cv2.circle(canvas.image, canvas.pixel((view.nearest.x, view.nearest.y)), 6, (255, 220, 0), 2, cv2.LINE_AA)
    if records:
        last = records[-1].pose
        body = footprint_polygon(last, params.body_length, params.body_width)
        cv2.polylines(canvas.image, [canvas.pixels(body)], True, (255, 255, 255), 2, cv2.LINE_AA)
    for stop in stops:
        cv2.drawMarker(canvas.image, canvas.pixel((stop["x"], stop["y"])), (255, 0, 255), cv2.MARKER_TILTED_CROSS,
                       14, 2)
    picture = with_key(canvas.image, [("safe", PALETTE[codes.SAFE]), ("hazard", HAZARD_RGB),
                                      ("unknown", PALETTE[codes.UNKNOWN]), ("corridor", (90, 160, 230)),
                                      ("nearest hazard", (255, 220, 0)), ("stop", (255, 0, 255))])
    states = {s: sum(1 for r in records if r.state == s) for s in ("clear", "hazard", "unknown")}
    return with_title(picture, f"hazard ({sensor}): {len(records)} frames, {states['hazard']} with a hazard in the "
                               f"path, {states['unknown']} unknown, {len(stops)} stops; last {len(views)} corridors")
