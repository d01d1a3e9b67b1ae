"""Place matchers for image-based routes: is the live view the stored one, and how far off is it?

An image-based route (seeds/image-based-route-maps.txt) is a chain of (image-before, action,
image-after) triplets; following it means comparing what the camera sees now with the stored images
(sec. 3.2), stopping an action when its image-after is seen, and making "adjust" actions when the
difference is small but not negligible (sec. 3.3). Every matcher here has the same interface
(`PlaceMatcher`): `describe` an image once into a compact descriptor (stored beside the route image,
so following a route never re-processes stored images), `similarity` of two descriptors, and
`match`, which decides "same place" and, where the matcher can tell, gives the image-plane shift,
rotation and scale that the adjust actions need.

Two matchers:
- `ContourMatcher` ("contour"): the paper's algorithm (sec. 3.5), step by step: 4x4-pixel cells,
  a brightness threshold, horizontal then vertical clustering, the main cluster's contour as 50
  points normalised by the centre-of-gravity-to-top distance, the count of similar point pairs.
  The paper reports that it fails when the lighting changes (sec. 4.2 (3)); the benchmark
  (tests/bench/bench_route_matchers.py) measures that.
- `FeatureMatcher` ("features", the default): ORB features on a CLAHE-normalised image, Lowe's ratio
  test and a RANSAC homography, in the spirit of Bearnav (reference/hopping-sfm-icp.md, "Teach and
  repeat"): the horizontal shift of the matched features is the heading correction. Local features
  on locally normalised contrast survive a moved sun where a global threshold does not.

Where sec. 3.5 is silent we chose, and say so at each step: colour becomes the mean of the channels
(the paper's RGB sum / 3, so one threshold fits both); "bright" is strictly above the threshold;
the object is the largest cluster; its contour is the outer border of its cells (holes ignored),
traced by OpenCV; the centre of gravity is the mean of its cells' centres; the 50 points are equally
spaced by arc length, start at the topmost contour point (the one the length is normalised by; on a
flat top, the cell above the centre of gravity) and run clockwise on screen, so point i of one image
is compared with point i of the other; a descriptor keeps the centre of gravity and the
normalising length in pixels, whose shift and ratio are the adjust offsets (sec. 3.3).

Images are grey (h, w) uint8 or colour (h, w, 3) uint8; pixel coordinates are OpenCV's (u right,
v down). Shifts are "live minus stored": a stored point at (u, v) is seen near (u + du, v + dv) now.
Only numpy, SciPy and OpenCV; no I/O.
"""
from __future__ import annotations

import io
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

__all__ = ["MatchResult", "PlaceMatcher", "ContourConfig", "ContourDescriptor", "ContourMatcher",
           "FeatureConfig", "FeatureDescriptor", "FeatureMatcher", "make_matcher", "MATCHER_NAMES",
           "DEFAULT_MATCHER", "heading_offset", "rank_route", "RankedMatch"]


# ============================================================================ the interface

@dataclass(frozen=True)
class MatchResult:
    """The verdict on a live view against a stored one.

    same_place: the matcher's decision (its thresholds are in its config).
    similarity: the matcher's score, higher = more similar, in [0, 1].
    shift_px: (du, dv) live minus stored, in live-image pixels; None where the matcher cannot tell.
        du > 0: the scene moved right in the image, i.e. the rover is turned left (counter-clockwise)
        of the stored heading; see `heading_offset`.
    rotation_rad: in-plane rotation live vs stored (counter-clockwise in the image, i.e. seen with
        v down, positive from u toward -v); None where unknown.
    scale: live size over stored size; > 1 means nearer than when stored (move backward), < 1
        farther (move forward); None where unknown.
    support: how many pieces of evidence the decision rests on (similar contour points, RANSAC
        inlier matches).
    far_shift_px: (du, dv) of the farthest matched points only (the top of a ground view): nearly
        free of the parallax a sideways offset adds, so it is the heading error alone; None where
        the matcher cannot tell.
    """

    same_place: bool
    similarity: float
    shift_px: tuple[float, float] | None = None
    rotation_rad: float | None = None
    scale: float | None = None
    support: int = 0
    far_shift_px: tuple[float, float] | None = None


@runtime_checkable
class PlaceMatcher(Protocol):
    """What route recording and following need from a matcher; see the module docstring."""

    name: str

    def describe(self, image: np.ndarray) -> Any: ...

    def similarity(self, desc_a: Any, desc_b: Any) -> float: ...

    def match(self, desc_live: Any, desc_stored: Any) -> MatchResult: ...

    def to_bytes(self, descriptor: Any) -> bytes: ...

    def from_bytes(self, data: bytes) -> Any: ...


def heading_offset(shift_u_px: float, focal_px: float) -> float:
    """Heading of the live view minus the stored one (radians, counter-clockwise positive, as the
    rover's heading) from the horizontal image shift: turning left by a moves the scene right by
    about f tan(a). The rover corrects by turning -heading_offset."""
    return math.atan2(shift_u_px, focal_px)


@dataclass(frozen=True)
class RankedMatch:
    index: int
    result: MatchResult


def rank_route(matcher: PlaceMatcher, live: Any, stored: Sequence[Any], top: int | None = None,
               shortlist: int = 10) -> list[RankedMatch]:
    """Match one live descriptor against a route's stored descriptors; best first.

    This is how the rover finds where on a route it is (sec. 3.2: "detect the current situation").
    A matcher with a cheap `quick_score` (FeatureMatcher: ratio-test matches, no RANSAC) has every
    stored image scored by it and only the `shortlist` best verified by `match`; the others are
    reported as not the same place, with similarity 0.
    """
    quick_score = getattr(matcher, "quick_score", None)
    if quick_score is None or len(stored) <= shortlist:
        chosen: range | np.ndarray = range(len(stored))
    else:
        scores = np.array([quick_score(live, d) for d in stored])
        chosen = np.argsort(-scores, kind="stable")[:shortlist]
    results = {int(i): matcher.match(live, stored[i]) for i in chosen}
    ranked = [RankedMatch(i, results.get(i, MatchResult(False, 0.0))) for i in range(len(stored))]
    ranked.sort(key=lambda r: (r.result.same_place, r.result.similarity), reverse=True)
    return ranked[:top] if top else ranked


def grey_image(image: np.ndarray) -> np.ndarray:
    """(h, w) uint8 from grey or BGR/RGB uint8 (mean of the channels: the paper's RGB sum / 3)."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        return np.asarray(np.mean(image[..., :3], axis=2, dtype=np.float32).round().astype(np.uint8))
    if image.ndim != 2:
        raise ValueError(f"images must be (h, w) or (h, w, 3), got shape {image.shape}")
    return image


# ---------------------------------------------------------------------- descriptor serialisation
# A descriptor is a small frozen dataclass of numpy arrays. Its bytes are a tag, then each array as
# (name, dtype, shape, raw little-endian data): compact, no pickle, readable without this code.

DESCRIPTOR_MAGIC = b"RVSD1"


def _pack_arrays(tag: str, arrays: dict[str, np.ndarray]) -> bytes:
    out = io.BytesIO()
    out.write(DESCRIPTOR_MAGIC)
    _write_text(out, tag)
    out.write(struct.pack("<B", len(arrays)))
    for name, array in arrays.items():
        array = np.asarray(array)              # keeps 0-d arrays 0-d, unlike ascontiguousarray
        dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
        _write_text(out, name)
        _write_text(out, dtype.str)
        out.write(struct.pack("<B", array.ndim))
        out.write(struct.pack(f"<{array.ndim}I", *array.shape))
        out.write(array.astype(dtype, copy=False).tobytes())
    return out.getvalue()


def _unpack_arrays(data: bytes, tag: str) -> dict[str, np.ndarray]:
    view = memoryview(data)
    if bytes(view[:len(DESCRIPTOR_MAGIC)]) != DESCRIPTOR_MAGIC:
        raise ValueError("not an RVS descriptor (bad magic)")
    at = len(DESCRIPTOR_MAGIC)
    found, at = _read_text(view, at)
    if found != tag:
        raise ValueError(f"descriptor is a {found!r} descriptor, expected {tag!r}")
    (count,), at = struct.unpack_from("<B", view, at), at + 1
    arrays = {}
    for _ in range(count):
        name, at = _read_text(view, at)
        dtype_str, at = _read_text(view, at)
        (ndim,), at = struct.unpack_from("<B", view, at), at + 1
        shape, at = struct.unpack_from(f"<{ndim}I", view, at), at + 4 * ndim
        dtype = np.dtype(dtype_str)
        size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        arrays[name] = np.frombuffer(view[at:at + size], dtype=dtype).reshape(shape).copy()
        at += size
    return arrays


def _write_text(out: io.BytesIO, text: str) -> None:
    raw = text.encode()
    out.write(struct.pack("<B", len(raw)))
    out.write(raw)


def _read_text(view: memoryview, at: int) -> tuple[str, int]:
    (length,) = struct.unpack_from("<B", view, at)
    return bytes(view[at + 1:at + 1 + length]).decode(), at + 1 + length


def _descriptor_arrays(descriptor: Any) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(getattr(descriptor, f.name)) for f in fields(descriptor)}


# ============================================================================ the paper's contour matcher

@dataclass(frozen=True)
class ContourConfig:
    """Settings of the contour matcher (paper sec. 3.5); the paper gives no values, these are ours.

    brightness_threshold: cells darker than this (mean grey 0-255 of the 4x4 pixels) are
        background (step 1-2). The paper's threshold is on the RGB sum; on grey images the mean of
        the channels is the sum / 3, so the same threshold works on either.
    relative_threshold: if set, the threshold is this times the image's mean cell brightness
        instead (not in the paper: a cheap answer to global brightness changes; off by default).
    cell_px: cell size (step 1-1: 4 by 4 pixels).
    contour_points: points on the contour compared (step 2: 50).
    point_tolerance: two corresponding normalised points are "similar" when closer than this, in
        units of the centre-of-gravity-to-top distance (step 3).
    min_similar_points: the two images match when at least this many of the pairs are similar.

    The defaults (100 of 255, i.e. above the regolith's ~70 at the simulated camera's fixed
    exposure; 0.3; half of the 50 points) favour precision in unchanged light on the tuning scenes
    (seeds 3, 5, 8). tests/bench/bench_route_matchers.py also prints the best any setting reaches.
    """

    brightness_threshold: float = 100.0
    relative_threshold: float | None = None
    cell_px: int = 4
    contour_points: int = 50
    point_tolerance: float = 0.3
    min_similar_points: int = 25

    def __post_init__(self) -> None:
        if not 0 < self.min_similar_points <= self.contour_points:
            raise ValueError(f"min_similar_points must be in 1..contour_points, got {self.min_similar_points}")
        if self.cell_px < 1 or self.contour_points < 3 or self.point_tolerance <= 0:
            raise ValueError("cell_px >= 1, contour_points >= 3 and point_tolerance > 0 are required")


@dataclass(frozen=True)
class ContourDescriptor:
    """The main cluster of one image, as the paper compares it.

    points: (n, 2) float32 contour points, origin at the cluster's centre of gravity, divided by the
        distance from it to the topmost contour point; all NaN when the image has no bright cluster.
    centroid_px: (2,) float32 centre of gravity in image pixels (u, v): its shift is the adjust offset.
    top_distance_px: float32 centre-of-gravity-to-top distance in pixels: its ratio is the scale.
    cell_count: int32 number of cells in the cluster.
    """

    points: np.ndarray
    centroid_px: np.ndarray
    top_distance_px: np.ndarray | np.floating
    cell_count: np.ndarray | np.integer

    @property
    def empty(self) -> bool:
        return bool(np.isnan(self.points).any())


def cell_brightness(image: np.ndarray, cell_px: int = 4) -> np.ndarray:
    """Step 1-1: the mean brightness of each cell_px x cell_px block (float32, (h // c, w // c)).
    A partial block at the right or bottom edge is dropped."""
    grey = grey_image(image)
    rows, cols = grey.shape[0] // cell_px, grey.shape[1] // cell_px
    blocks = grey[:rows * cell_px, :cols * cell_px].reshape(rows, cell_px, cols, cell_px)
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def bright_cells(cells: np.ndarray, config: ContourConfig) -> np.ndarray:
    """Step 1-2: True where a cell is above the threshold; the rest is background."""
    threshold = config.brightness_threshold
    if config.relative_threshold is not None:
        threshold = config.relative_threshold * float(cells.mean())
    return cells > threshold


def horizontal_runs(bright: np.ndarray) -> np.ndarray:
    """Step 1-3: horizontally neighbouring bright cells form one cluster, a run.

    Returns (n, 3) int64 rows (row, first column, last column), in row-major order.
    """
    padded = np.zeros((bright.shape[0], bright.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = bright
    edges = np.diff(padded, axis=1)                 # +1 where a run starts, -1 just after it ends
    start_rows, start_cols = np.nonzero(edges == 1)
    _, end_cols = np.nonzero(edges == -1)            # same row-major order, one end per start
    return np.stack([start_rows, start_cols, end_cols - 1], axis=1).astype(np.int64)


def merge_vertical_runs(runs: np.ndarray) -> np.ndarray:
    """Step 1-4: runs on neighbouring rows that share a column are integrated into one cluster.

    Returns the cluster label of each run (0..k-1). Vertical contact means column overlap between
    runs of rows r and r + 1 (4-connectivity, as the paper's "vertically neighbouring").
    """
    if len(runs) == 0:
        return np.zeros(0, dtype=np.int64)
    below_a, below_b = _overlapping_runs_on_next_row(runs)
    graph = coo_matrix((np.ones(len(below_a)), (below_a, below_b)), shape=(len(runs), len(runs)))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def _overlapping_runs_on_next_row(runs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (a, b): run b lies on the row below run a and shares at least one column.

    Runs are in row-major order and disjoint on a row, so the runs of row r + 1 that start at or
    before a's last column are one contiguous slice; of those, the ones that end at or after a's
    first column touch it.
    """
    row, first, last = runs[:, 0], runs[:, 1], runs[:, 2]
    width = int(last.max()) + 2
    key = row * width + first                                        # sorted: row, then column
    lo = np.searchsorted(key, (row + 1) * width)                     # first run on row r + 1
    hi = np.searchsorted(key, (row + 1) * width + last, side="right")  # past the last starting <= a's end
    counts = hi - lo
    a = np.repeat(np.arange(len(runs)), counts)
    b = lo[a] + np.arange(len(a)) - np.repeat(np.cumsum(counts) - counts, counts)
    touching = last[b] >= first[a]
    return a[touching], b[touching]


def main_cluster(bright: np.ndarray) -> np.ndarray:
    """Steps 1-3 and 1-4, then the object: the largest cluster (in cells) as a bool mask.

    The paper extracts "an object" without saying which when there are several; we take the
    largest, the one most likely to be seen again. All False when nothing is bright.
    """
    runs = horizontal_runs(bright)
    mask = np.zeros_like(bright, dtype=bool)
    if len(runs) == 0:
        return mask
    labels = merge_vertical_runs(runs)
    lengths = runs[:, 2] - runs[:, 1] + 1
    largest = int(np.argmax(np.bincount(labels, weights=lengths)))
    for row, first, last in runs[labels == largest]:
        mask[row, first:last + 1] = True
    return mask


def cluster_contour(mask: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """Step 2: the outer contour of the cluster, (m, 2) float64 cell coordinates (x, y), clockwise
    on screen (v down) and starting at the topmost point.

    The paper leaves open where the 50 points start and which way they run; the correspondence of
    point i with point i needs both fixed. We start at the topmost point, the one the length is
    normalised by, and where the top is flat, at its cell nearest the centre of gravity's column
    (the flat top's middle, stable under small shifts). Holes are ignored: the paper matches the
    object's outline.
    """
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=len).reshape(-1, 2).astype(np.float64)
    if _signed_area(contour) < 0:
        contour = contour[::-1]
    top = np.lexsort((np.abs(contour[:, 0] - centroid[0]), contour[:, 1]))[0]
    return np.roll(contour, -top, axis=0)


def _signed_area(polygon: np.ndarray) -> float:
    """Shoelace area; positive when the polygon runs clockwise on screen (v down)."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def resample_closed(polygon: np.ndarray, count: int) -> np.ndarray:
    """Step 2: `count` points at equal arc-length intervals round a closed polygon, from its first
    vertex. A single-point polygon (a one-cell cluster) gives that point `count` times."""
    closed = np.vstack([polygon, polygon[:1]])
    steps = np.hypot(*np.diff(closed, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    if arc[-1] == 0:
        return np.repeat(polygon[:1], count, axis=0)
    targets = np.arange(count) * (arc[-1] / count)
    return np.stack([np.interp(targets, arc, closed[:, 0]), np.interp(targets, arc, closed[:, 1])], axis=1)


def normalise_contour(points: np.ndarray, centroid: np.ndarray) -> tuple[np.ndarray, float]:
    """Step 2: origin at the centre of gravity, lengths over its distance to the topmost contour
    point (the first point, see `cluster_contour`). Returns the points and that distance."""
    top_distance = float(np.hypot(*(points[0] - centroid)))
    if top_distance == 0:
        top_distance = 1.0      # a one-cell cluster: nothing to normalise by
    return (points - centroid) / top_distance, top_distance


class ContourMatcher:
    """The paper's matcher (sec. 3.5); see ContourConfig for the thresholds and what they mean."""

    name = "contour"

    def __init__(self, config: ContourConfig | None = None):
        self.config = config or ContourConfig()

    def describe(self, image: np.ndarray) -> ContourDescriptor:
        c = self.config
        cells = cell_brightness(image, c.cell_px)                     # 1-1
        mask = main_cluster(bright_cells(cells, c))                   # 1-2, 1-3, 1-4
        if not mask.any():
            nan = np.full((c.contour_points, 2), np.nan, np.float32)
            return ContourDescriptor(nan, np.full(2, np.nan, np.float32), np.float32(np.nan), np.int32(0))
        rows, cols = np.nonzero(mask)
        centroid = np.array([cols.mean(), rows.mean()])               # C.G. of the cluster's cells
        contour = resample_closed(cluster_contour(mask, centroid), c.contour_points)   # 2: 50 points
        points, top_distance = normalise_contour(contour, centroid)
        # Cell (i, j) covers pixels [c*j, c*j + c); its centre is at c*j + (c - 1) / 2.
        centroid_px = centroid * c.cell_px + (c.cell_px - 1) / 2
        return ContourDescriptor(points.astype(np.float32), centroid_px.astype(np.float32),
                                 np.float32(top_distance * c.cell_px), np.int32(len(rows)))

    def similar_points(self, desc_a: ContourDescriptor, desc_b: ContourDescriptor) -> int:
        """Step 3: how many corresponding points lie within point_tolerance of each other."""
        if desc_a.empty or desc_b.empty:
            return 0
        distances = np.hypot(*(desc_a.points - desc_b.points).T)
        return int(np.count_nonzero(distances < self.config.point_tolerance))

    def similarity(self, desc_a: ContourDescriptor, desc_b: ContourDescriptor) -> float:
        return self.similar_points(desc_a, desc_b) / self.config.contour_points

    def match(self, desc_live: ContourDescriptor, desc_stored: ContourDescriptor) -> MatchResult:
        similar = self.similar_points(desc_live, desc_stored)
        if similar == 0:
            return MatchResult(False, 0.0)
        # The paper's adjust knowledge (sec. 3.3): the object's offset and its size ratio.
        shift = desc_live.centroid_px - desc_stored.centroid_px
        scale = float(desc_live.top_distance_px / desc_stored.top_distance_px)
        return MatchResult(similar >= self.config.min_similar_points, similar / self.config.contour_points,
                           shift_px=(float(shift[0]), float(shift[1])), scale=scale, support=similar)

    def to_bytes(self, descriptor: ContourDescriptor) -> bytes:
        return _pack_arrays(self.name, _descriptor_arrays(descriptor))

    def from_bytes(self, data: bytes) -> ContourDescriptor:
        return ContourDescriptor(**_unpack_arrays(data, self.name))


# ============================================================================ the default: local features

@dataclass(frozen=True)
class FeatureConfig:
    """Settings of the feature matcher.

    The defaults were chosen on rendered scenes of seeds 3, 5 and 8 (the benchmark measures on
    other seeds): 480 px beat 640 under a moved sun, as did 4 CLAHE tiles over 8 and 16 and 4 ORB
    levels over 8; 1000 features gained a few points of recall for four times the matching time.

    work_width: images are resized to this width before detection (speed, and the same detail
        whatever the camera's resolution); keypoints are reported in the input's pixels.
    clahe_clip, clahe_tiles: contrast-limited adaptive histogram equalisation, so a brighter or
        dimmer scene and shadowed parts give similar local contrast.
    features, orb_levels, orb_scale_factor, orb_fast_threshold: the ORB detector. Each keypoint
        costs 40 bytes of descriptor (32 bytes + two float32 coordinates).
    ratio: Lowe's ratio test: a match is kept when its distance is below ratio x the second best.
    ransac_px: RANSAC reprojection tolerance of the homography, in work-image pixels.
    min_inliers: the views are the same place when the homography has at least this many inliers
        (different places gave at most 12 on the tuning scenes)...
    min_inlier_ratio: ...and they are at least this share of the ratio-test matches...
    scale_range: ...and the live view's scale against the stored one is within this range (a place
        seen from much nearer or farther is another place on the route). Fewer ratio-test matches
        than min_inliers skip RANSAC: the cheap rejection that keeps matching a whole route fast.
    """

    work_width: int = 480
    clahe_clip: float = 2.0
    clahe_tiles: int = 4
    features: int = 500
    orb_levels: int = 4
    orb_scale_factor: float = 1.2
    orb_fast_threshold: int = 10
    ratio: float = 0.8
    ransac_px: float = 4.0
    min_inliers: int = 15
    min_inlier_ratio: float = 0.25
    scale_range: tuple[float, float] = (0.7, 1.4)

    def __post_init__(self) -> None:
        if self.work_width < 64 or self.features < 8 or not 0 < self.ratio <= 1:
            raise ValueError("work_width >= 64, features >= 8 and 0 < ratio <= 1 are required")
        if self.min_inliers < 4:
            raise ValueError(f"a homography needs at least 4 matches: min_inliers >= 4, got {self.min_inliers}")


@dataclass(frozen=True)
class FeatureDescriptor:
    """ORB keypoints of one image.

    points: (n, 2) float32 keypoint positions in the input image's pixels (u, v).
    descriptors: (n, 32) uint8 ORB descriptors.
    work_scale: float32 work-image pixels per input pixel (converts the RANSAC tolerance).
    """

    points: np.ndarray
    descriptors: np.ndarray
    work_scale: np.ndarray | np.floating

    def __len__(self) -> int:
        return len(self.points)


class FeatureMatcher:
    """ORB on CLAHE, ratio test, RANSAC homography; see FeatureConfig for the thresholds."""

    name = "features"

    def __init__(self, config: FeatureConfig | None = None):
        self.config = config or FeatureConfig()
        c = self.config
        self._clahe = cv2.createCLAHE(clipLimit=c.clahe_clip, tileGridSize=(c.clahe_tiles, c.clahe_tiles))
        self._orb = cv2.ORB_create(nfeatures=c.features, scaleFactor=c.orb_scale_factor, nlevels=c.orb_levels,
                                   fastThreshold=c.orb_fast_threshold)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)

    def normalised(self, image: np.ndarray) -> tuple[np.ndarray, float]:
        """The work image: resized to work_width and CLAHE-equalised; and its scale."""
        grey = grey_image(image)
        scale = self.config.work_width / grey.shape[1]
        if scale != 1:
            size = (self.config.work_width, max(1, round(grey.shape[0] * scale)))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        return self._clahe.apply(grey), scale

    def describe(self, image: np.ndarray) -> FeatureDescriptor:
        work, scale = self.normalised(image)
        keypoints, descriptors = self._orb.detectAndCompute(work, None)
        if descriptors is None or not keypoints:
            return FeatureDescriptor(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.float32(scale))
        points = np.array([k.pt for k in keypoints], dtype=np.float32) / np.float32(scale)
        return FeatureDescriptor(points, descriptors, np.float32(scale))

    def ratio_matches(self, desc_a: FeatureDescriptor, desc_b: FeatureDescriptor) -> np.ndarray:
        """(k, 2) index pairs (a, b) that pass Lowe's ratio test, a's best neighbour in b."""
        if len(desc_a) < 2 or len(desc_b) < 2:
            return np.zeros((0, 2), np.int64)
        knn = self._matcher.knnMatch(desc_a.descriptors, desc_b.descriptors, k=2)
        pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn
                 if len(m) == 2 and m[0].distance < self.config.ratio * m[1].distance]
        return np.array(pairs, dtype=np.int64).reshape(-1, 2)

    def quick_score(self, desc_a: FeatureDescriptor, desc_b: FeatureDescriptor) -> float:
        """Ratio-test matches only (no RANSAC, a fifth of `match`'s time): for shortlisting."""
        return float(len(self.ratio_matches(desc_a, desc_b)))

    def similarity(self, desc_a: FeatureDescriptor, desc_b: FeatureDescriptor) -> float:
        return self.match(desc_a, desc_b).similarity

    def match(self, desc_live: FeatureDescriptor, desc_stored: FeatureDescriptor) -> MatchResult:
        c = self.config
        pairs = self.ratio_matches(desc_live, desc_stored)
        if len(pairs) < c.min_inliers:                  # cannot reach min_inliers: skip RANSAC
            return MatchResult(False, 0.0, support=0)
        live, stored = desc_live.points[pairs[:, 0]], desc_stored.points[pairs[:, 1]]
        tolerance = c.ransac_px / float(desc_live.work_scale)
        homography, inlier_mask = cv2.findHomography(stored, live, cv2.RANSAC, tolerance, maxIters=2000,
                                                     confidence=0.995)
        if homography is None:
            return MatchResult(False, 0.0, support=0)
        inliers = inlier_mask.ravel().astype(bool)
        count = int(inliers.sum())
        # Similarity: the inliers' share of the smaller keypoint set, so it is comparable across images.
        similarity = min(1.0, count / max(1, min(len(desc_live), len(desc_stored))))
        shift, rotation, scale = _image_motion(stored[inliers], live[inliers])
        far_shift = _far_shift(stored[inliers], live[inliers])
        same = (count >= c.min_inliers and count >= c.min_inlier_ratio * len(pairs)
                and scale is not None and c.scale_range[0] <= scale <= c.scale_range[1])
        return MatchResult(bool(same), similarity, shift_px=shift, rotation_rad=rotation, scale=scale,
                           support=count, far_shift_px=far_shift)

    def to_bytes(self, descriptor: FeatureDescriptor) -> bytes:
        return _pack_arrays(self.name, _descriptor_arrays(descriptor))

    def from_bytes(self, data: bytes) -> FeatureDescriptor:
        return FeatureDescriptor(**_unpack_arrays(data, self.name))


def _far_shift(stored: np.ndarray, live: np.ndarray, share: float = 0.3,
               least: int = 5) -> tuple[float, float] | None:
    """Median displacement of the highest `share` of the matched points in the image (the farthest
    ground in a forward view), or None if fewer than `least` of them."""
    if len(stored) < least:
        return None
    far = stored[:, 1] <= np.quantile(stored[:, 1], share)
    if far.sum() < least:
        return None
    du, dv = np.median(live[far] - stored[far], axis=0)
    return float(du), float(dv)


def _image_motion(stored: np.ndarray,
                  live: np.ndarray) -> tuple[tuple[float, float] | None, float | None, float | None]:
    """Shift, rotation and scale for the adjust actions, from matched inlier points.

    The shift is the median displacement (robust, and Bearnav's horizontal-shift mode in spirit:
    under a heading change every point moves by about f tan(a)); rotation and scale come from a
    least-squares similarity transform of the inliers.
    """
    if len(stored) < 3:
        return None, None, None
    shift = np.median(live - stored, axis=0)
    similarity, _ = cv2.estimateAffinePartial2D(stored, live, method=cv2.LMEDS)
    if similarity is None:
        return (float(shift[0]), float(shift[1])), None, None
    a, b = float(similarity[0, 0]), float(similarity[1, 0])
    # In v-down image coordinates a counter-clockwise-on-screen turn has a negative angle.
    return (float(shift[0]), float(shift[1])), -math.atan2(b, a), math.hypot(a, b)


# ============================================================================ factory

MATCHER_NAMES = ("features", "contour")
DEFAULT_MATCHER = "features"


def make_matcher(name: str = DEFAULT_MATCHER, config: Any = None) -> PlaceMatcher:
    """The matcher called `name`, with its config (or its defaults)."""
    if name == "features":
        return FeatureMatcher(config)
    if name == "contour":
        return ContourMatcher(config)
    raise ValueError(f"unknown matcher {name!r}; known: {', '.join(MATCHER_NAMES)}")
