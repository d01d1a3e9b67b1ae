"""The person candidates in one cloud: what stands on the ground, each judged by its shape."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .person import BANDS, UPPER_LEGS, PersonModel, Shape, person_confidence, shape_of
from .standing import Cluster, Plane, StandingParams, ground_of, standing_clusters


@dataclass(frozen=True)
class Candidate:
    shape: Shape
    confidence: float
    terms: dict[str, float]      # each membership the confidence is made of
    points: np.ndarray           # the cluster's points (N, 3, world), for pictures

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.shape.x, self.shape.y])

    def range_from(self, xy: np.ndarray) -> float:
        return float(math.hypot(self.shape.x - xy[0], self.shape.y - xy[1]))


def candidates(points: np.ndarray, sensor_xy: np.ndarray, plane: Plane,
               params: StandingParams = StandingParams(), model: PersonModel = PersonModel()) -> list[Candidate]:
    """Every standing cluster of a world cloud (N, 3), most person-like first."""
    if len(points) < params.min_points:
        return []
    ground = ground_of(points, plane, params, sensor_xy=sensor_xy)
    clusters = standing_clusters(points, ground, params, sensor_xy)
    found = [judged(cluster, sensor_xy, model, params) for cluster in clusters]
    return sorted(found, key=lambda c: -c.confidence)


def judged(cluster: Cluster, sensor_xy: np.ndarray, model: PersonModel, params: StandingParams,
           legs_band: tuple[float, float] = BANDS["legs"]) -> Candidate:
    """One cluster's shape and how person-like it is, its legs measured in `legs_band` above the
    sensor's floor for them."""
    shape = shape_of(cluster, sensor_xy, model, legs_band, legs_floor(cluster, sensor_xy, params))
    confidence, terms = person_confidence(shape, model)
    return Candidate(shape, confidence, terms, cluster.points)


def legs_floor(cluster: Cluster, sensor_xy: np.ndarray, params: StandingParams) -> float:
    """How high above its ground a cluster's legs are measured: for a noisy sensor, one deviation clear
    of where its points start to stand, since the ground's noise tail just above that joins the
    cluster beside the feet and widens the legs band (stereo at 7 m: 0.49 m, sigma 0.12 m)."""
    if params.noise_per_m2 <= 0:
        return 0.0
    range_m = float(np.linalg.norm(np.median(cluster.points[:, :2], axis=0) - np.asarray(sensor_xy, dtype=float)))
    return float(params.min_above_at(range_m) + params.noise_at(range_m))


def above_the_feet(candidate: Candidate, sensor_xy: np.ndarray, model: PersonModel = PersonModel(),
                   params: StandingParams = StandingParams()) -> Candidate:
    """The candidate judged again with its legs taken above the knees, clear of a low rock at its feet
    that joined the cluster (person.py's notes: for a tracker that expects a person there)."""
    return judged(Cluster(candidate.points, candidate.shape.ground_z, True), sensor_xy, model, params, UPPER_LEGS)
