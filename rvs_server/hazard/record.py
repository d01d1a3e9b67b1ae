"""What hazard detection keeps: one record per frame (its event and its CSV row), written to
frames.csv as the activity goes (FrameLog), and the product `hazard-stop` closes: corridor.png (the
memory around the rover, the last frames' corridors and detections, the stops) and the manifest."""
from __future__ import annotations

import csv
import math
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Any, TextIO

import cv2
import numpy as np

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
                _number(truth[0]), _number(truth[1]),
                _number(math.degrees(truth[2]) if truth[2] == truth[2] else None, 2),
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


PATH_KEPT = 20_000        # poses kept for the picture's path (about an hour at 5 Hz)
LATENCY_BIN_MS = 0.05     # the latency histogram's bin (percentiles to this), up to LATENCY_TOP_MS
LATENCY_TOP_MS = 5000.0


class FrameLog:
    """frames.csv and stops.csv written as the activity goes, a row per frame or stop, flushed at once:
    a kill loses at most the frame in progress. In memory only what the summary and the picture need
    (counts per state, a latency histogram, the last PATH_KEPT poses, the stops), not every frame: an
    activity may run for a season."""

    def __init__(self, product: Any):
        self._lock = threading.Lock()
        self._frames = self._open(product.add("frames.csv", "one row per frame, written as it was taken: state, "
                                              "nearest hazard in the path (distance from the leading edge, world "
                                              "x y, cause), latency, the estimate and (simulated) the true pose"),
                                  FRAME_COLUMNS)
        self._stops = self._open(product.add("stops.csv", "every drive the guard stopped, written as it stopped: "
                                             "where, why and (simulated) the true pose and free way left to the "
                                             "nearest true obstacle"), STOP_COLUMNS)
        self.states = {"clear": 0, "hazard": 0, "unknown": 0}
        self.latency = np.zeros(int(LATENCY_TOP_MS / LATENCY_BIN_MS) + 1, dtype=np.int64)
        self.path: deque[tuple[float, float]] = deque(maxlen=PATH_KEPT)
        self.last: FrameRecord | None = None
        self.stops: list[dict] = []

    @staticmethod
    def _open(path: Any, header: list[str]) -> tuple[TextIO, Any]:
        handle = open(path, "w", newline="", encoding="utf-8")   # noqa: SIM115 (open for the activity's life)
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(header)
        handle.flush()
        return handle, writer

    def frame(self, record: FrameRecord) -> None:
        with self._lock:
            handle, writer = self._frames
            if not handle.closed:
                writer.writerow(record.row())
                handle.flush()
            self.states[record.state] += 1
            if record.state != "unknown":
                self.latency[min(int(record.latency_ms / LATENCY_BIN_MS), len(self.latency) - 1)] += 1
            self.path.append((record.pose.x, record.pose.y))
            self.last = record

    def stop(self, stop: dict) -> None:
        with self._lock:
            handle, writer = self._stops
            if not handle.closed:
                writer.writerow(stop_row(stop))
                handle.flush()
            self.stops.append(stop)

    @property
    def frames(self) -> int:
        return sum(self.states.values())

    def latency_percentile(self, q: float) -> float | None:
        """The q-th percentile of the measured frames' latency (ms, to the bin's upper edge); None: none."""
        total = int(self.latency.sum())
        if total == 0:
            return None
        index = int(np.searchsorted(np.cumsum(self.latency), q / 100.0 * total))
        return (min(index, len(self.latency) - 1) + 1) * LATENCY_BIN_MS

    def close(self) -> None:
        with self._lock:
            for handle, _ in (self._frames, self._stops):
                handle.close()


def stop_row(stop: dict) -> list[Any]:
    truth = stop.get("truth") or {}
    heading = truth.get("heading_rad")
    return [stop["seq"], f"{stop['sim_s']:.3f}", f"{stop['x']:.3f}", f"{stop['y']:.3f}", f"{stop['heading_deg']:.2f}",
            _number(truth.get("x")), _number(truth.get("y")),
            _number(math.degrees(heading) if heading is not None else None, 2),
            _number(truth.get("clearance_m")), truth.get("contacts", ""), stop["reason"]]


def write_product(product: Any, log: FrameLog, views: list[CorridorView], memory: HazardMemory,
                  params: CorridorParams, settings: Any, sensor: str) -> None:
    log.close()
    picture = corridor_picture(log, views, memory, params, sensor)
    if picture is not None:
        write_png(product.add("corridor.png", "the hazard memory around the rover (north up): the last frames' "
                              "corridors, detections and stops"), picture)
    p50, p95 = log.latency_percentile(50), log.latency_percentile(95)
    product.note("summary", {
        "sensor": sensor, "frames": log.frames, "stops": len(log.stops), "states": dict(log.states),
        "latency_ms": {"p50": p50, "p95": p95} if p50 is not None else None,
        "corridor": {"reach_m": params.reach, "half_width_m": params.half_width, "cell_m": params.cell},
        "settings": settings.model_dump(mode="json")})
    product.finish()


PALETTE = {codes.SAFE: (70, 110, 70), codes.UNKNOWN: (25, 25, 25)}
HAZARD_RGB = (220, 50, 40)


def corridor_picture(log: FrameLog, views: list[CorridorView], memory: HazardMemory, params: CorridorParams,
                     sensor: str) -> np.ndarray | None:
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
    canvas.line(list(log.path), (240, 240, 240), 1)
    for view in views:
        x0, y0, heading = view.pose
        outline = footprint_polygon(RoverPose(x0 + math.cos(heading) * params.reach / 2,
                                              y0 + math.sin(heading) * params.reach / 2, 0.0, heading),
                                    params.body_length + params.reach, 2 * params.half_width)
        cv2.polylines(canvas.image, [canvas.pixels(outline)], True, (90, 160, 230), 1, cv2.LINE_AA)
        if view.nearest is not None:
            cv2.circle(canvas.image, canvas.pixel((view.nearest.x, view.nearest.y)), 6, (255, 220, 0), 2, cv2.LINE_AA)
    if log.last is not None:
        last = log.last.pose
        body = footprint_polygon(last, params.body_length, params.body_width)
        cv2.polylines(canvas.image, [canvas.pixels(body)], True, (255, 255, 255), 2, cv2.LINE_AA)
    for stop in log.stops:
        cv2.drawMarker(canvas.image, canvas.pixel((stop["x"], stop["y"])), (255, 0, 255), cv2.MARKER_TILTED_CROSS,
                       14, 2)
    picture = with_key(canvas.image, [("safe", PALETTE[codes.SAFE]), ("hazard", HAZARD_RGB),
                                      ("unknown", PALETTE[codes.UNKNOWN]), ("corridor", (90, 160, 230)),
                                      ("nearest hazard", (255, 220, 0)), ("stop", (255, 0, 255))])
    states = log.states
    return with_title(picture, f"hazard ({sensor}): {log.frames} frames, {states['hazard']} with a hazard in the "
                               f"path, {states['unknown']} unknown, {len(log.stops)} stops; "
                               f"last {len(views)} corridors")
