"""Is a standing cluster a person, and where does it stand? Geometry only, from a 3-D sensor.

A detector trained on images would need weights from elsewhere and has never seen a rendered suit;
the shape a range sensor measures says it directly. Seen from the sensor, a person is

- as tall as a person (1.5-2.1 m above the ground it stands on),
- narrow across the line of sight: 0.25-0.65 m at the torso (0.5 facing, 0.3 side-on),
- narrower at the legs than at the torso, arms included (a boulder is widest at its foot),
- topped by a head narrower than the shoulders or no wider (side-on the two are close).

Each is a soft membership (a trapezoid: 1 inside the usual range, falling to 0 at the edges); the
confidence is their geometric mean, so one clear mismatch rejects and small ones only lower it.

The centre: where the person stands, between the legs. A range sensor sees the near side of a body.
Across the line of sight the centre is the middle of the legs band's extent; along it, the median of
that band's points plus the depth of the legs behind their visible face, which depends on how the
person is turned, and the measured width says that: legs W wide and D deep seen facing show W
across and their face lies D/2 before the centre, side-on they show D across and lie W/2 before;
between, the offset is taken as linear in the width (`shape_of`). Where the width is not measured
well (a stereo matcher widens a 0.2 m leg by 2-3 pixels each side, 5-8 cm at 6 m, which read a
side-on walker as facing: 5-8 cm short), the walk's heading says how the person is turned: the
nearest face of a W x D box turned by theta from the line of sight lies D/2 |cos theta| +
W/2 |sin theta| before its centre (`centre_facing`). The legs, not the torso: what a person carries
(an astronaut's backpack) is not where it stands, and a torso band's middle would follow it. Where
the legs are hidden (a rock before them), the torso band serves the same way, with the body's size.

A low rock at a person's feet joins its cluster and widens the legs band (0.35 m legs read 0.5-0.6 m
beside a 0.35 m rock, stereo seed 418: the frame was no person, and the centre moved 6-10 cm towards
the rock). The legs above the knees (`UPPER_LEGS`) are clear of such rocks; they are not the search's
band, because an irregular boulder can be narrower there than at its middle (TOF seed 416: 0.44 m
under 0.52, a person by every measure), while at its foot it is wide. A tracker that already follows
a person may judge a cluster where it expects it by them (`shape_of(..., legs_band=UPPER_LEGS)`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .standing import Cluster


@dataclass(frozen=True)
class Trapezoid:
    """Membership 1 on [low, high], falling linearly to 0 at [zero_low, zero_high]."""

    zero_low: float
    low: float
    high: float
    zero_high: float

    def __call__(self, value: float) -> float:
        if not math.isfinite(value):
            return 0.0
        if value < self.low:
            return float(np.clip((value - self.zero_low) / (self.low - self.zero_low), 0.0, 1.0))
        if value > self.high:
            return float(np.clip((self.zero_high - value) / (self.zero_high - self.high), 0.0, 1.0))
        return 1.0


@dataclass(frozen=True)
class PersonModel:
    height: Trapezoid = Trapezoid(1.25, 1.5, 2.1, 2.4)
    torso_width: Trapezoid = Trapezoid(0.15, 0.25, 0.65, 0.85)
    legs_to_torso: Trapezoid = Trapezoid(0.0, 0.0, 0.85, 1.0)
    head_to_torso: Trapezoid = Trapezoid(0.0, 0.0, 1.05, 1.35)
    body_width: float = 0.5      # m: across the shoulders, arms included (the centre's offset)
    body_depth: float = 0.3      # m: front to back, without a backpack
    legs_width: float = 0.35     # m: across both legs, standing
    legs_depth: float = 0.2      # m: a leg front to back
    body_reach_m: float = 0.4    # along the line of sight, how far from its middle a body's points lie
    min_leg_points: int = 30     # fewer seen at the legs (a rock before them): the centre from the torso
    min_points: int = 40


@dataclass(frozen=True)
class Shape:
    """What a cluster measures, seen from `sensor` (world x, y)."""

    height: float                # top above the ground under it
    torso_width: float           # extent across the line of sight, torso band (45-80 % of the height)
    legs_width: float            # the same, legs band (10-40 %); nan when not seen (below the view)
    head_width: float            # the same, head band (88-100 %)
    points: int
    x: float                     # the estimated centre of the body, world
    y: float
    ground_z: float
    face: tuple[float, float] = (math.nan, math.nan)   # the middle of the visible face of `part`, world x, y
    sight: tuple[float, float] = (1.0, 0.0)            # unit, world: from the sensor to the body
    part: str = "legs"           # the band the centre was taken from: legs, or torso where they were hidden

    def fields(self) -> dict[str, float]:
        return {"height_m": self.height, "torso_width_m": self.torso_width, "legs_width_m": self.legs_width,
                "head_width_m": self.head_width, "points": self.points}


BANDS = {"legs": (0.10, 0.40), "torso": (0.45, 0.80), "head": (0.88, 1.00)}
UPPER_LEGS = (0.22, 0.42)        # the legs above the knees, below the hands
EXTENT_PERCENTILES = (3, 97)     # a band's extent across: robust to a few stray points at its sides


def shape_of(cluster: Cluster, sensor_xy: np.ndarray, model: PersonModel = PersonModel(),
             legs_band: tuple[float, float] = BANDS["legs"], legs_floor_m: float = 0.0) -> Shape:
    """What a cluster measures (see the module's notes), its legs band between the shares `legs_band`
    of its height and no lower than `legs_floor_m` above its ground."""
    points = cluster.points
    height = cluster.height
    up = (points[:, 2] - cluster.ground_z) / max(height, 1e-6)
    middle = np.median(points[:, :2], axis=0)
    sight = middle - np.asarray(sensor_xy, dtype=float)
    sight /= max(np.linalg.norm(sight), 1e-9)
    across = np.array([-sight[1], sight[0]])
    lateral = (points[:, :2] - middle) @ across
    radial = (points[:, :2] - middle) @ sight

    # Points far before or behind the body's middle along the line of sight are not the body: a
    # stereo matcher smears depth edges into streaks that would widen the legs.
    on_body = np.abs(radial - np.median(radial)) <= model.body_reach_m

    def band(name: str) -> np.ndarray:
        low, high = legs_band if name == "legs" else BANDS[name]
        if name == "legs":
            low = max(low, legs_floor_m / max(height, 1e-6))
        return (up >= low) & (up <= high) & on_body

    def extent(mask: np.ndarray) -> float:
        if mask.sum() < 5:
            return math.nan
        low, high = np.percentile(lateral[mask], EXTENT_PERCENTILES)
        return float(high - low)

    torso, legs = band("torso"), band("legs")
    if torso.sum() < 5:   # what is seen of it is not a body's middle: fall back to everything
        torso = np.ones(len(points), dtype=bool)
    width = extent(torso)
    if legs.sum() >= model.min_leg_points:
        part, part_width, part_depth = legs, model.legs_width, model.legs_depth
    else:
        part, part_width, part_depth = torso, model.body_width, model.body_depth
    low, high = np.percentile(lateral[part], EXTENT_PERCENTILES)
    behind = float(np.clip((part_width + part_depth) / 2 - (high - low) / 2, part_depth / 2, part_width / 2))
    face = middle + across * (low + high) / 2 + sight * float(np.median(radial[part]))
    centre = face + sight * behind
    return Shape(height, width, extent(legs), extent(band("head")), len(points),
                 float(centre[0]), float(centre[1]), cluster.ground_z, (float(face[0]), float(face[1])),
                 (float(sight[0]), float(sight[1])), "legs" if part is legs else "torso")


def centre_facing(shape: Shape, heading: np.ndarray, model: PersonModel = PersonModel()) -> np.ndarray:
    """The body's centre (world x, y) from its visible face and the direction it faces or walks
    (`heading`, world, any length), instead of from its measured width."""
    width, depth = (model.legs_width, model.legs_depth) if shape.part == "legs" else \
        (model.body_width, model.body_depth)
    h = np.asarray(heading, dtype=float) / max(float(np.linalg.norm(heading)), 1e-9)
    sight = np.asarray(shape.sight, dtype=float)
    along = abs(float(sight @ h))
    behind = depth / 2 * along + width / 2 * math.sqrt(max(0.0, 1.0 - along ** 2))
    return np.asarray(shape.face, dtype=float) + sight * behind


def person_confidence(shape: Shape, model: PersonModel = PersonModel()) -> tuple[float, dict[str, float]]:
    """The confidence that `shape` is a person (0..1) and each membership it is made of. A band the
    sensor did not see (legs below the view at close range) does not count against it."""
    terms = {"height": model.height(shape.height), "torso_width": model.torso_width(shape.torso_width)}
    if math.isfinite(shape.legs_width):
        terms["legs_to_torso"] = model.legs_to_torso(shape.legs_width / shape.torso_width)
    if math.isfinite(shape.head_width):
        terms["head_to_torso"] = model.head_to_torso(shape.head_width / shape.torso_width)
    terms["points"] = min(1.0, shape.points / model.min_points)
    values = np.array(list(terms.values()))
    confidence = 0.0 if (values <= 0).any() else float(np.exp(np.log(values).mean()))
    return confidence, terms
