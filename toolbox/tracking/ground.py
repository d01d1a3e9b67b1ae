"""The ground under a walking target, from the ground heights measured under its feet frame by frame.

A running average over time lags on a slope by the slope times the distance walked over the
average's memory (0.3 per frame at 10 Hz and 1.5 m/s: a 10 % slope read 3-4 cm behind), and the
lag has the walk's sign, so it does not average out. The ground is a function of place, not of
time: each estimate here is a local plane fitted to the recent samples weighted by their distance
from the query place (locally weighted regression), its slope held towards a prior (the rover's own
ground plane) where the samples cannot tell it (across a straight walk, or a target standing still).
On a plane the estimate has no lag at all; standing still, it is the mean of the samples there.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GroundTrailParams:
    radius_m: float = 0.5          # the Gaussian weight's sigma over the distance from the query place
    memory_s: float = 4.0          # samples older than this are forgotten (a walk's ground changes)
    max_samples: int = 60
    height_sigma_m: float = 0.03   # one sample's noise ...
    slope_sigma: float = 0.15      # ... against how far the slope may stray from the prior


class GroundTrail:
    """Ground samples (x, y, z) under a target, and the ground estimated at any place near them."""

    def __init__(self, params: GroundTrailParams = GroundTrailParams()):
        self.params = params
        self._samples: deque[tuple[float, float, float, float]] = deque(maxlen=params.max_samples)

    def __len__(self) -> int:
        return len(self._samples)

    def add(self, x: float, y: float, z: float, time_s: float) -> None:
        self._samples.append((float(x), float(y), float(z), float(time_s)))
        while self._samples and time_s - self._samples[0][3] > self.params.memory_s:
            self._samples.popleft()

    def height_at(self, x: float, y: float, slope: tuple[float, float] = (0.0, 0.0)) -> float | None:
        """The ground height at (x, y); `slope` (dz/dx, dz/dy) is the prior the fit leans to. None
        without samples."""
        if not self._samples:
            return None
        data = np.array(self._samples)
        d = data[:, :2] - (x, y)
        w = np.exp(-0.5 * np.sum(d ** 2, axis=1) / self.params.radius_m ** 2)
        prior = np.asarray(slope, dtype=float)
        # Minimise sum w (z - a - b.d)^2 + lam |b - prior|^2: the normal equations in (a, b).
        lam = (self.params.height_sigma_m / self.params.slope_sigma) ** 2
        design = np.column_stack([np.ones(len(d)), d])
        normal = design.T @ (design * w[:, None])
        rhs = design.T @ (w * data[:, 2])
        normal[1:, 1:] += lam * np.eye(2)
        rhs[1:] += lam * prior
        if normal[0, 0] < 1e-9:   # every sample far from here: the nearest stands in
            return float(data[np.argmin(np.sum(d ** 2, axis=1)), 2])
        return float(np.linalg.solve(normal, rhs)[0])
