"""One target followed in the ground plane: a constant-velocity Kalman filter with gating.

State (x, y, vx, vy), world frame; the process noise is white acceleration of spectral density `q`
((m/s^2)^2 s: how hard a walker can stop or turn), the measurement a position with its covariance.
A measurement is taken only inside the gate (its squared Mahalanobis distance to the prediction
under the chi-square bound, 99 % for two degrees of freedom), so a boulder beside the path is not
mistaken for the person passing it. Without a measurement the track coasts on its prediction, its
uncertainty (and so its gate) growing with the time unseen, until `max_coast_s`: then it is lost.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GATE_CHI2_99 = 9.21   # chi-square, 2 degrees of freedom, 99 %


@dataclass(frozen=True)
class TrackParams:
    q: float = 2.0                 # (m/s^2)^2 s: white-acceleration spectral density
    max_coast_s: float = 4.0       # unseen this long: lost
    gate_chi2: float = GATE_CHI2_99
    min_gate_m: float = 0.4        # the gate is never narrower: a body's outline jitters by this much
    max_speed: float = 3.0         # m/s: a faster estimate is clipped (a walker, not a vehicle)


@dataclass
class Track:
    """The filter's belief: state (4,), covariance (4, 4), when it was last predicted and seen."""

    state: np.ndarray
    covariance: np.ndarray
    time_s: float
    seen_s: float
    params: TrackParams = field(default_factory=TrackParams)

    @classmethod
    def start(cls, xy: np.ndarray, measurement_cov: np.ndarray, time_s: float,
              params: TrackParams = TrackParams(), speed_sigma: float = 1.0) -> Track:
        """A track born at a measurement, its velocity unknown (0 with `speed_sigma` per axis)."""
        covariance = np.zeros((4, 4))
        covariance[:2, :2] = measurement_cov
        covariance[2:, 2:] = np.eye(2) * speed_sigma ** 2
        return cls(np.array([xy[0], xy[1], 0.0, 0.0]), covariance, time_s, time_s, params)

    # -- the model ------------------------------------------------------------------------------
    @staticmethod
    def transition(dt: float) -> np.ndarray:
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        return f

    def process_noise(self, dt: float) -> np.ndarray:
        q = self.params.q
        block = np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]]) * q
        noise = np.zeros((4, 4))
        for axis in range(2):
            index = np.ix_([axis, axis + 2], [axis, axis + 2])
            noise[index] = block
        return noise

    # -- one frame ------------------------------------------------------------------------------
    def predicted(self, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        """State and covariance at `time_s`, the track itself unchanged."""
        dt = max(0.0, time_s - self.time_s)
        f = self.transition(dt)
        return f @ self.state, f @ self.covariance @ f.T + self.process_noise(dt)

    def predict(self, time_s: float) -> None:
        self.state, self.covariance = self.predicted(time_s)
        self.time_s = max(self.time_s, time_s)

    def distance2(self, xy: np.ndarray, measurement_cov: np.ndarray) -> float:
        """Squared Mahalanobis distance of a measurement to the current prediction."""
        innovation = np.asarray(xy, dtype=float) - self.state[:2]
        s = self.covariance[:2, :2] + measurement_cov
        return float(innovation @ np.linalg.solve(s, innovation))

    def in_gate(self, xy: np.ndarray, measurement_cov: np.ndarray) -> bool:
        near = np.linalg.norm(np.asarray(xy, dtype=float) - self.state[:2]) <= self.params.min_gate_m
        return bool(near or self.distance2(xy, measurement_cov) <= self.params.gate_chi2)

    def update(self, xy: np.ndarray, measurement_cov: np.ndarray) -> None:
        h = np.zeros((2, 4))
        h[0, 0] = h[1, 1] = 1.0
        s = h @ self.covariance @ h.T + measurement_cov
        gain = np.linalg.solve(s, h @ self.covariance).T
        self.state = self.state + gain @ (np.asarray(xy, dtype=float) - h @ self.state)
        joseph = np.eye(4) - gain @ h   # the Joseph form keeps the covariance symmetric and positive
        self.covariance = joseph @ self.covariance @ joseph.T + gain @ measurement_cov @ gain.T
        speed = float(np.hypot(*self.state[2:]))
        if speed > self.params.max_speed:
            self.state[2:] *= self.params.max_speed / speed
        self.seen_s = self.time_s

    def unseen_s(self) -> float:
        return self.time_s - self.seen_s

    @property
    def lost(self) -> bool:
        return self.unseen_s() > self.params.max_coast_s

    @property
    def position(self) -> np.ndarray:
        return self.state[:2].copy()

    @property
    def velocity(self) -> np.ndarray:
        return self.state[2:].copy()
