"""What tracking keeps and shows: the search's candidates (candidates.csv, detect.png) and the track
(track.csv, track.png: the path over the ground the frames saw, with the truth when simulated)."""
from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from rvs_server.files import save_npz_atomic, write_text_atomic
from rvs_server.products.canvas import Canvas, side_by_side
from rvs_server.products.rasters import write_png
from toolbox.colour import colourise, with_key, with_title
from toolbox.grid import GridSpec
from toolbox.tracking.detect import Candidate

PICTURE_CELL = 0.05
PERSON = (255, 64, 160)
OTHER = (90, 200, 255)
TRUTH = (60, 220, 60)
ROVER = (255, 255, 255)


def _f(value: float | None, digits: int = 3) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _csv(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return out.getvalue()


@dataclass(frozen=True)
class Judged:
    """A candidate as the search reports it: where from the rover, and whether it counts as a person."""

    candidate: Candidate
    range_m: float
    bearing_deg: float
    person: bool
    seen_s: float = math.nan          # simulation time of the view that saw it
    repeated: bool = False            # another view's sighting of a person or thing listed before it


# ------------------------------------------------------------------------------------- the search
def write_candidates(product: Any, judged: list[Judged]) -> None:
    header = ["rank", "person", "confidence", "x", "y", "z", "range_m", "bearing_deg", "height_m", "torso_width_m",
              "legs_width_m", "head_width_m", "points", "terms"]
    rows = []
    for rank, j in enumerate(judged, 1):
        s = j.candidate.shape
        rows.append([rank, int(j.person), _f(j.candidate.confidence), _f(s.x), _f(s.y), _f(s.ground_z),
                     _f(j.range_m), _f(j.bearing_deg, 2), _f(s.height), _f(s.torso_width), _f(s.legs_width),
                     _f(s.head_width), s.points,
                     " ".join([f"{k}={v:.2f}" for k, v in j.candidate.terms.items()]
                              + (["repeat"] if j.repeated else []))])
    write_text_atomic(product.add("candidates.csv", "every standing cluster the search found, most person-like "
                                  "first: its centre (x, y, ground z, world), range and bearing (degrees, positive "
                                  "right) from the PTU, shape, confidence and the memberships it is made of"),
                      _csv(header, rows))


def write_views(product: Any, views: Sequence[Any]) -> None:
    """The search's views as it judged them, so that a search is judged again offline (a changed
    detector on the same clouds): per view its world points, the sensor's place, the rover's plane."""
    arrays: dict[str, np.ndarray] = {}
    for index, view in enumerate(views):
        plane = view.plane
        arrays[f"points_{index}"] = view.points.astype(np.float32)
        arrays[f"sensor_{index}"] = np.array([*view.sensor_xy, view.sensor_z, view.pan_deg, view.tilt_deg,
                                              view.sim_s])
        arrays[f"plane_{index}"] = np.array([plane.x0, plane.y0, plane.z0, plane.gx, plane.gy])
    save_npz_atomic(product.add("views.npz", "each view of the search: points_K (N, 3 world, metres), sensor_K "
                                "(x, y, z of the sensor, pan and tilt in degrees, simulation seconds), plane_K (the "
                                "rover's ground plane: x0, y0, z0, gx, gy)"), arrays, compressed=True)


def _ground_canvas(points: np.ndarray, around: np.ndarray, reach: float) -> tuple[Canvas, np.ndarray]:
    """A north-up picture of a cloud's highest point per cell around `around` (x, y), and its grid."""
    spec = GridSpec.covering((around[0] - reach, around[0] + reach), (around[1] - reach, around[1] + reach),
                             PICTURE_CELL)
    row, col, inside = spec.cell_of(points[:, 0], points[:, 1])
    top = np.full(spec.shape, np.nan)
    if inside.any():
        flat = np.full(spec.rows * spec.cols, -np.inf)
        np.maximum.at(flat, row[inside] * spec.cols + col[inside], points[inside, 2])
        top = np.where(np.isfinite(flat), flat, np.nan).reshape(spec.shape)
    low, high = (np.nanpercentile(top, [2, 99.5]) if np.isfinite(top).any() else (0.0, 1.0))
    rgb = colourise(top, float(low), float(max(high, low + 0.5)))
    return Canvas(rgb, spec, 640), top


def _silhouette(candidate: Candidate, sensor_xy: np.ndarray, label: str, colour) -> np.ndarray:
    """The candidate's points as the sensor saw them: across the line of sight against height."""
    points, shape = candidate.points, candidate.shape
    sight = np.array([shape.x, shape.y]) - sensor_xy
    sight /= max(np.linalg.norm(sight), 1e-9)
    across = (points[:, :2] - [shape.x, shape.y]) @ np.array([sight[1], -sight[0]])   # positive right
    up = points[:, 2] - shape.ground_z
    size, scale = 220, 100.0   # pixels, pixels per metre: 2.2 m tall
    image = np.full((size, 160, 3), 24, dtype=np.uint8)
    u = np.clip((across * scale + 80).astype(int), 0, 159)
    v = np.clip((size - 1 - up * scale).astype(int), 0, size - 1)
    image[v, u] = colour
    for metres in (0.5, 1.0, 1.5, 2.0):
        y = int(size - 1 - metres * scale)
        cv2.line(image, (0, y), (6, y), (160, 160, 160), 1)
    cv2.putText(image, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def write_search_picture(product: Any, points: np.ndarray, sensor_xy: np.ndarray, judged: list[Judged],
                         reach: float, truth: dict | None) -> None:
    canvas, _ = _ground_canvas(points, sensor_xy, reach)
    cv2.circle(canvas.image, canvas.pixel(sensor_xy), 6, ROVER, -1)
    judged = [j for j in judged if not j.repeated]     # the repeats are in candidates.csv
    for rank, j in enumerate(judged, 1):
        centre = canvas.pixel(j.candidate.xy)
        colour = PERSON if j.person else OTHER
        cv2.circle(canvas.image, centre, 12, colour, 2)
        cv2.putText(canvas.image, f"{rank}: {j.candidate.confidence:.2f}", (centre[0] + 14, centre[1] - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    if truth is not None:
        pixel = canvas.pixel((truth["x"], truth["y"]))
        cv2.drawMarker(canvas.image, pixel, TRUTH, cv2.MARKER_CROSS, 18, 2)
    found = sum(j.person for j in judged)
    picture = with_key(canvas.image, [("person", PERSON), ("standing, not a person", OTHER), ("rover", ROVER)]
                       + ([("true astronaut", TRUTH)] if truth is not None else []))
    picture = with_title(picture, f"track3d-detect: {found} person(s) among {len(judged)} standing clusters "
                                  f"(highest point per 5 cm cell, north up)")
    panels = [_silhouette(j.candidate, sensor_xy, f"{rank}: {j.candidate.confidence:.2f} "
                          f"h {j.candidate.shape.height:.2f} m", PERSON if j.person else OTHER)
              for rank, j in enumerate(judged[:6], 1)]
    if panels:
        picture = side_by_side([picture, np.concatenate(panels[:3], axis=0)] +
                               ([np.concatenate(panels[3:], axis=0)] if len(panels) > 3 else []))
    write_png(product.add("detect.png", "the search seen from above (highest point per cell), every candidate "
                          "ringed with its rank and confidence, and each one's silhouette as the sensor saw it "
                          "(across the line of sight against height, 1 px = 1 cm)"), picture)


# ------------------------------------------------------------------------------------- the track
@dataclass
class TrackRecord:
    seq: int
    sim_s: float
    state: str                       # tracking | lost | unknown
    seen: bool                       # a measurement was taken this frame (not coasting)
    x: float
    y: float
    z: float
    vx: float
    vy: float
    sigma_m: float
    range_m: float
    bearing_deg: float
    confidence: float
    pan_deg: float
    tilt_deg: float
    ptu_command: str
    grab_ms: float
    process_ms: float
    candidates: int
    reason: str = ""
    truth: dict | None = None
    best: str = ""                   # the most person-like cluster: confidence @ metres from the prediction
    measured: tuple[float, float, float, float] | None = None   # the frame's measurement: x, y, ground z, height

    def event(self) -> dict[str, Any]:
        if self.state == "unknown":
            return {"state": "unknown", "reason": self.reason}
        return {"state": self.state, "x": _f(self.x), "y": _f(self.y), "z": _f(self.z), "vx": _f(self.vx, 2),
                "vy": _f(self.vy, 2), "range": _f(self.range_m, 2), "bearing": _f(self.bearing_deg, 1),
                "seen": int(self.seen)}

    def row(self) -> list[Any]:
        t = self.truth or {}
        return [self.seq, f"{self.sim_s:.3f}", self.state, int(self.seen), _f(self.x), _f(self.y), _f(self.z),
                _f(self.vx), _f(self.vy), _f(self.sigma_m), _f(self.range_m), _f(self.bearing_deg, 2),
                _f(self.confidence), *(_f(v) for v in (self.measured or (math.nan,) * 4)),
                _f(self.pan_deg, 3), _f(self.tilt_deg, 3), self.ptu_command,
                _f(self.grab_ms, 1), _f(self.process_ms, 1), self.candidates, self.best, self.reason,
                _f(t.get("x")), _f(t.get("y")), _f(t.get("z")), _f(t.get("visible"), 3),
                _f(t.get("pan_deg"), 3), _f(t.get("tilt_deg"), 3)]


TRACK_HEADER = ["seq", "sim_s", "state", "seen", "x", "y", "z", "vx", "vy", "sigma_m", "range_m", "bearing_deg",
                "confidence", "measured_x", "measured_y", "measured_z", "measured_height_m",
                "pan_deg", "tilt_deg", "ptu_command", "grab_ms", "process_ms", "candidates",
                "best_candidate", "reason",
                "true_x", "true_y", "true_z", "true_visible", "true_pan_deg", "true_tilt_deg"]


def write_track(product: Any, records: list[TrackRecord], points: np.ndarray, sensor_xy: np.ndarray,
                summary: dict[str, Any]) -> None:
    write_text_atomic(product.add("track.csv", "every frame: state (tracking, lost, unknown), seen (1: measured, "
                                  "0: coasting on the prediction), the filter's position (x, y; z the ground under "
                                  "it; world), velocity, 1-sigma, range and bearing from the PTU, the frame's own "
                                  "measurement where it took one (x, y, the ground under it, the person's height), "
                                  "the PTU's angles and command, wall milliseconds; simulated, the astronaut's "
                                  "true place and the share of it in view"),
                      _csv(TRACK_HEADER, [r.row() for r in records]))
    placed = [r for r in records if r.state != "unknown" and math.isfinite(r.x)]
    truth = np.array([[r.truth["x"], r.truth["y"]] for r in records if r.truth])
    xy = np.array([[r.x, r.y] for r in placed]) if placed else np.zeros((0, 2))
    everything = np.concatenate([xy, truth.reshape(-1, 2), sensor_xy[None]])
    centre = (everything.min(axis=0) + everything.max(axis=0)) / 2
    reach = max(2.0, float(np.abs(everything - centre).max()) + 1.0)
    canvas, _ = _ground_canvas(points, centre, reach) if len(points) else (None, None)
    if canvas is None:
        spec = GridSpec.covering((centre[0] - reach, centre[0] + reach), (centre[1] - reach, centre[1] + reach),
                                 PICTURE_CELL)
        canvas = Canvas(np.full((*spec.shape, 3), 40, dtype=np.uint8), spec, 640)
    if len(truth) > 1:
        canvas.line(truth, TRUTH, 2)
    for a, b in zip(placed[:-1], placed[1:], strict=True):
        colour = PERSON if b.state == "tracking" and b.seen else ((255, 200, 0) if b.state == "tracking" else OTHER)
        cv2.line(canvas.image, canvas.pixel((a.x, a.y)), canvas.pixel((b.x, b.y)), colour, 2, cv2.LINE_AA)
    cv2.circle(canvas.image, canvas.pixel(sensor_xy), 6, ROVER, -1)
    picture = with_key(canvas.image, [("tracked (measured)", PERSON), ("coasting", (255, 200, 0)), ("lost", OTHER),
                                    ("rover", ROVER)] + ([("true path", TRUTH)] if len(truth) else []))
    title = (f"track3d: {summary['frames']} frames, tracked {summary['tracked']}"
             + (f", position RMSE {100 * summary['rmse_m']:.1f} cm" if summary.get("rmse_m") is not None else ""))
    write_png(product.add("track.png", "the track over the ground the frames saw (highest point per 5 cm cell, "
                          "north up): measured, coasting and lost stretches, the true path when simulated"),
              with_title(picture, title))


__all__ = ["Judged", "TrackRecord", "write_candidates", "write_search_picture", "write_track", "write_views"]
