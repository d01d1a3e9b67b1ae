"""track3d-start's activity: the target followed in 3-D at frame rate, the PTU kept on it.

Per frame: borrow the PTU and the sensor (a job that holds either makes the frame `unknown`), take
one frame where the unit stands (read before and after: it may still be turning), give the devices
back; make world points of it and the person candidates (toolbox/tracking); predict the track to the
frame's instant and take the nearest candidate inside the gate that is person-like enough (a rock may
hide the legs, so less than the search asks); none: the track coasts on its prediction, and after
`max_coast_s` unseen, or once the prediction leaves the sensor's range, it is lost: the PTU holds on
where it was last for `max_coast_s`, then sweeps the pan (lost_sweep_pan_deg), and any clearly
person-like candidate in view takes the target up again (the same target: one person, one
identity). Then borrow the PTU once more and point it where the
target will be at the next frame, if the aim is off by more than the dead band, at a speed that gets
it there in one frame period and no faster than `max_ptu_speed_deg_s`.

While it runs the PTU is claimed (devices/sharing.py): a job that would move it is `409 busy`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from rvs_server.activities import Activity
from toolbox.tracking.detect import Candidate, above_the_feet, candidates
from toolbox.tracking.ground import GroundTrail
from toolbox.tracking.kalman import Track
from toolbox.tracking.person import centre_facing
from toolbox.tracking.standing import Plane

from .record import TrackRecord, write_track
from .settings import TrackingSettings
from .sight import Seen, Sight

if TYPE_CHECKING:
    from rvs_server.host import Host

PICTURE_POINTS = 200_000     # the ground the picture shows: a sample of every frame's points
NEAR_GROUND_M = 6.0          # within this the ground round a person's feet is seen well (its height learnt)
HEIGHT_FRAMES = 50           # the person's height: the median of this many near frames
FEET_HIDDEN_M = 0.1          # the feet's ground this far from the head's top less the height: hidden
RESTART_HEIGHT_M = 0.2       # a track restarts only on a person this near the target's height
CONFIRM_M = 0.5              # acquiring: a person seen again this near (plus a walker's way) is confirmed
STEER_SHARE = 0.5            # the PTU is asked to arrive within this share of a frame period: it stands
                             # again before the next frame is taken


@dataclass(frozen=True)
class Target:
    """What track3d-detect found last: where the nearest person stood, when, with which sensor."""

    x: float
    y: float
    z: float
    height: float
    confidence: float
    sensor: str
    sim_s: float
    product: str
    range_m: float = math.inf    # from the PTU when the search saw it


class TrackActivity(Activity):
    kind = "track"

    def __init__(self, server: Host, settings: TrackingSettings, sensor: str, rate_hz: float, target: Target,
                 product: Any):
        super().__init__(server, rate_hz)
        self.settings, self.sensor, self.product = settings, sensor, product
        self.sight = Sight(server, settings, sensor, settings.stereo_track_resolution)
        self.model = settings.person(sensor)
        self.standing = settings.standing(sensor, self.sight.resolution)
        # The track is born where and when the search saw the target, its speed unknown up to a
        # walker's: by the first frame its gate has grown by all the search's time since. Until it
        # first takes a measurement it wants a person as sure as a lost track does.
        sigma = settings.sigma_m(sensor, 5.0, self.sight.resolution)
        self.track = Track.start(np.array([target.x, target.y]), np.eye(2) * sigma ** 2, target.sim_s,
                                 settings.track(sensor), speed_sigma=settings.walk_speed_m_s / 2)
        self.track.seen_s = max(target.sim_s, server.clock.now())   # coasting counts from the start
        self.locked = False
        self.ground_z = target.z
        self._ground_trail = GroundTrail()         # the ground measured under the target, where it walked
        # The search's height seeds the person's height only where it is a whole grown person's seen
        # near, as a frame's is learnt: a search at range may have had the head above its view (a
        # 1.44 m "person" 1.80 m tall made every later frame's ground 0.35 m high, the feet's ground
        # taken for hidden), and a stereo search at 7.6 m read the ground 0.22 m high (1.53 m tall).
        whole = self.model.height(target.height) >= 1.0 and target.range_m <= NEAR_GROUND_M
        self._heights: list[float] = [target.height] if whole else []
        self._far_heights: list[float] = []        # whole grown-person heights seen beyond NEAR_GROUND_M
        self._last_xy: np.ndarray | None = None   # where the target was last measured
        self.lost = False
        self._lost_s = -math.inf                  # when it was lost (simulation seconds)
        self._sweep_to: float | None = None       # lost: the pan end the PTU sweeps to
        self._sightings: list[tuple[float, np.ndarray]] = []   # acquiring: the last frame's whole people
        self.records: list[TrackRecord] = []
        self._picture: list[np.ndarray] = []
        self._picture_count = 0
        self.sensor_xy = np.array([target.x, target.y])
        self._ptu_speed_deg_s: float | None = None     # the speed the PTU was last set to, by this activity

    def start(self) -> None:
        self.server.devices.sharing.claim("ptu", self.kind)
        super().start()

    # -- one frame ---------------------------------------------------------------------------------
    def frame(self, seq: int) -> dict[str, Any]:
        devices = self.server.devices
        with devices.sharing.borrow("ptu", self.sight.frames.device) as busy:
            if busy is not None:
                return self.unknown(seq, f"a job holds the {busy}")
            grabbed = self.sight.grab(devices, self._ptu_speed_deg_s)
        seen = self.sight.seen(grabbed)
        found = candidates(seen.points, seen.sensor_xy, self._fallback_plane(seen), self.standing,
                           self.model)
        chosen = self._follow(seen, found)
        if chosen is not None:
            self._last_xy = chosen.xy
        command = self._steer(devices, seen)
        record = self._record(seq, seen, chosen, len(found), command)
        if found:
            best = found[0]
            weakest = min(best.terms, key=best.terms.get)
            record = replace(record, best=f"{best.confidence:.2f}@{np.linalg.norm(best.xy - self.track.position):.2f}"
                                          + (f" {weakest}={best.terms[weakest]:.2f}" if best.confidence < 1 else ""))
        self.records.append(record)
        self._keep_for_picture(seen)
        self.sensor_xy = seen.sensor_xy
        return record.event()

    def _fallback_plane(self, seen: Seen) -> Plane:
        """Where the frame saw no ground near the target (its feet below the view at close range), the
        rover's plane through the target's last known ground height."""
        x, y = self.track.position
        rover = seen.plane
        return Plane(float(x), float(y), self.ground_z, rover.gx, rover.gy)

    def _follow(self, seen: Seen, found: list[Candidate]) -> Candidate | None:
        settings, track = self.settings, self.track
        if self.locked and not self.lost:
            track.predict(seen.sim_s)
            chosen = self._nearest_in_gate(seen, self._target_like(seen, found, settings.track_confidence))
            if chosen is not None:
                chosen = self._centred_by_heading(chosen)
                track.update(chosen.xy, self._measurement_cov(seen, chosen))
                self._ground(chosen, seen)
                return chosen
            chosen = self._within_reach(seen, found)
            if chosen is not None:   # it turned back where the prediction went on: one target, taken up there
                self.track = Track.start(chosen.xy, self._measurement_cov(seen, chosen), seen.sim_s,
                                         settings.track(self.sensor), speed_sigma=settings.walk_speed_m_s / 2)
                self._ground(chosen, seen)
                return chosen
            if track.lost or self._beyond_range(seen):
                self._lose(seen)
            return None
        # Acquiring (after the start) or lost: only a whole person (not cut by the edge of the view,
        # where a boulder's part can look like one), seen as one in two frames running, takes it up.
        people = [c for c in found if c.confidence >= settings.reacquire_confidence
                  and not self.sight.cut_by_view(seen, c.points)]
        confirmed = self._confirmed(seen, people)
        if not self.lost:
            track.predict(seen.sim_s)
            if not self._looks_at(seen, track.position):
                # Still turning from the search's last view to where it saw the target: what this
                # frame sees is elsewhere (a boulder passed on the way took the track: TOF seed 417),
                # and the time to find it there counts from when the unit looks there.
                track.seen_s = seen.sim_s
                return None
            chosen = self._nearest_in_gate(seen, confirmed)
            if chosen is not None:
                track.update(chosen.xy, self._measurement_cov(seen, chosen))
                self.locked = True
                self._ground(chosen, seen)
                return chosen
            if track.unseen_s() > settings.acquire_s:
                self._lose(seen)
            return None
        if not confirmed:
            return None
        chosen = min(confirmed, key=lambda c: c.range_from(seen.sensor_xy))
        self.track = Track.start(chosen.xy, self._measurement_cov(seen, chosen), seen.sim_s,
                                 settings.track(self.sensor))
        self.lost, self._sweep_to, self.locked = False, None, True
        self._ground(chosen, seen)
        return chosen

    def _target_like(self, seen: Seen, found: list[Candidate], threshold: float) -> list[Candidate]:
        """The candidates at least `threshold` person-like to be the target it follows: as the search
        judges them, or, where only their legs fail and they stand as tall as the target, judged by the
        legs above the knees: a low rock at the walker's feet joined the cluster and widened its legs
        (stereo seed 418 coasted 10-15 frames on at a corner, 1.8 m off, whenever the walker stood by
        one)."""
        heights_known = bool(self._heights or self._far_heights)
        judged = []
        for candidate in found:
            if (candidate.confidence < threshold and heights_known
                    and min(candidate.terms, key=candidate.terms.get) == "legs_to_torso"
                    and abs(self._height_off(candidate)) <= RESTART_HEIGHT_M):
                candidate = above_the_feet(candidate, seen.sensor_xy, self.model, self.standing)
            if candidate.confidence >= threshold:
                judged.append(candidate)
        return judged

    def _centred_by_heading(self, chosen: Candidate) -> Candidate:
        """The candidate with its centre taken from the walk's heading (the track's velocity) where
        the settings say so for this sensor and the target walks; otherwise as it is."""
        velocity = self.track.velocity
        if not self.settings.centre_from_heading.of(self.sensor) or \
                float(np.linalg.norm(velocity)) < self.settings.heading_min_speed_m_s:
            return chosen
        x, y = centre_facing(chosen.shape, velocity, self.model)
        return replace(chosen, shape=replace(chosen.shape, x=float(x), y=float(y)))

    def _within_reach(self, seen: Seen, found: list[Candidate]) -> Candidate | None:
        """Outside the gate, a clearly person-like candidate no farther from where the target was last
        measured than a walker gets since (plus a body): a walker who stopped or turned back where the
        constant-velocity prediction went on (at 5 Hz a reversal at 1.2 m/s left it 0.7-1.0 m outside
        a gate the filter had grown sure of, and the track coasted off: stereo seed 415)."""
        if self._last_xy is None:
            return None
        reach = self.settings.walk_speed_m_s * max(0.0, seen.sim_s - self.track.seen_s) + CONFIRM_M
        near = [c for c in self._target_like(seen, found, self.settings.reacquire_confidence)
                if float(np.linalg.norm(c.xy - self._last_xy)) <= reach and not self.sight.cut_by_view(seen, c.points)
                and abs(self._height_off(c)) <= RESTART_HEIGHT_M]
        return min(near, key=lambda c: float(np.linalg.norm(c.xy - self._last_xy)), default=None)

    def _nearest_in_gate(self, seen: Seen, found: list[Candidate]) -> Candidate | None:
        """The candidate in the gate nearest the prediction. The gate is the sensor's: a cluster of the
        wrong height is no likelier to be the target for being unsure (the widened covariance let a
        1.3 m cluster 1.6 m off in, stereo seed 407), it only weighs less once chosen."""
        chosen, best = None, math.inf
        for candidate in found:
            cov = self.settings.measurement_cov(self.sensor, candidate.xy - seen.sensor_xy, self.sight.resolution)
            if self.track.in_gate(candidate.xy, cov):
                distance = self.track.distance2(candidate.xy, cov)
                if distance < best:
                    chosen, best = candidate, distance
        return chosen

    def _confirmed(self, seen: Seen, people: list[Candidate]) -> list[Candidate]:
        """The people this frame that the frame before also saw, no farther off than a walker gets
        between them plus a body (M of N track initiation, two of two)."""
        before, self._sightings = self._sightings, [(seen.sim_s, c.xy) for c in people]
        speed = self.settings.walk_speed_m_s
        return [c for c in people
                if any(np.linalg.norm(c.xy - xy) <= CONFIRM_M + speed * (seen.sim_s - t) for t, xy in before)]

    def _looks_at(self, seen: Seen, xy: np.ndarray) -> bool:
        """Whether the frame's view takes in the place xy (its bearing within the field of view)."""
        bearing, _ = self.sight.bearing_range(seen.pose, xy)
        return abs((bearing - seen.pan_deg + 180.0) % 360.0 - 180.0) <= self.sight.half_fov_deg[0]

    def _beyond_range(self, seen: Seen) -> bool:
        """The unseen target's prediction has left the sensor's range: no frame can confirm it there,
        and coasting on follows only an extrapolation (the campaign's walkers stood still out there,
        while the estimate walked on: every such frame a false positive)."""
        return float(np.linalg.norm(self.track.position - seen.sensor_xy)) > self.settings.max_range_m

    def _lose(self, seen: Seen) -> None:
        self.lost, self.locked = True, False
        self.track.state[2:] = 0.0        # hold where it was last believed while the PTU sweeps
        self._lost_s = seen.sim_s

    def _ground(self, chosen: Candidate, seen: Seen) -> None:
        """The target's ground height: the ground its feet stand on (toolbox/tracking/standing.py
        step 5). Where that disagrees with the top of the head less the person's height (learnt near,
        where the ground is seen well, or until then farther out) by more than FEET_HIDDEN_M, the feet
        are hidden (a rock before them: the lowest points seen are a leg's) and the top less the
        height stands in."""
        shape = chosen.shape
        top = np.array([shape.x, shape.y, shape.ground_z + shape.height])
        whole = self.sight.sees_top_of(seen, top)
        near = chosen.range_from(seen.sensor_xy) <= NEAR_GROUND_M
        grown = self.model.height(shape.height) >= 1.0
        if whole and near and grown:
            # Only a grown person's height is learnt, near too: 1.35-1.5 m clusters (a body cut short
            # by the boulder at 5.7-5.9 m) learnt there made every later frame's ground 0.3-0.5 m
            # high (stereo seed 407).
            self._heights.append(shape.height)
        elif whole and grown:
            # Farther out a grown person's height stands in until one is seen near: a walker who
            # stays beyond 6 m had no height at all, and a frame with its feet hidden read the
            # ground at its legs (0.45 m high: TOF seed 407 coming out from behind the boulder).
            self._far_heights.append(shape.height)
        measured = shape.ground_z
        heights = self._heights or self._far_heights
        if whole and heights:
            from_top = top[2] - float(np.median(heights[-HEIGHT_FRAMES:]))
            if abs(measured - from_top) > FEET_HIDDEN_M:
                measured = from_top
        # The ground as a function of place (a local plane over where the target walked), not a
        # running average over time, which lagged on slopes by the distance walked over its memory.
        self._ground_trail.add(shape.x, shape.y, measured, seen.sim_s)
        height = self._ground_trail.height_at(shape.x, shape.y, slope=(seen.plane.gx, seen.plane.gy))
        self.ground_z = measured if height is None else height

    def _measurement_cov(self, seen: Seen, candidate: Candidate) -> np.ndarray:
        """The sensor's covariance for the frame's centre, widened by how far the cluster's height is
        from the target's: a body cut short (legs behind a rock, the top out of view) or merged with a
        rock has its centre off by 0.2-1.5 m (stereo seed 403: every frame over 0.2 m off read
        0.1-0.5 m short or tall), and one such frame should not pull the track."""
        cov = self.settings.measurement_cov(self.sensor, candidate.xy - seen.sensor_xy, self.sight.resolution)
        return cov * (1.0 + (self._height_off(candidate) / self.settings.shape_height_sigma_m) ** 2)

    def _height_off(self, candidate: Candidate) -> float:
        """How much taller (positive) the candidate stands than the target's learnt height; 0 while
        none is known."""
        heights = self._heights or self._far_heights
        return candidate.shape.height - float(np.median(heights[-HEIGHT_FRAMES:])) if heights else 0.0

    def _steer(self, devices: Any, seen: Seen) -> str:
        """Point the PTU where the target will be at the next frame; the command sent, or why none."""
        if self.lost:
            return self._look_around(devices, seen)
        state, _ = self.track.predicted(seen.sim_s + 1.0 / self.rate_hz)
        return self._aim_at(devices, seen, state[:2])

    def _aim_at(self, devices: Any, seen: Seen, xy: np.ndarray) -> str:
        """Point the PTU at a person standing at xy, within a frame period and the unit's speeds."""
        settings = self.settings
        period = 1.0 / self.rate_hz
        aim_at = np.array([xy[0], xy[1], self.ground_z + settings.aim_height_m])
        pan, tilt = self.sight.aim(seen.pose, aim_at)
        low, high = settings.tilt_limits_deg
        tilt = float(np.clip(tilt, low, high))
        with devices.sharing.borrow("ptu") as busy:
            if busy is not None:
                return "busy"
            driver = devices.ptu.ready_driver()
            limits = driver.limits
            pan = float(np.clip(pan, *limits.range_deg("pan")))
            tilt = float(np.clip(tilt, *limits.range_deg("tilt")))
            now_pan, now_tilt = seen.pan_deg, seen.tilt_deg
            off = max(abs(pan - now_pan), abs(tilt - now_tilt))
            if off <= settings.deadband_deg:
                return "none"
            low_speed, high_speed = limits.speed_range_deg_s("pan")
            speed = float(np.clip(off / (STEER_SHARE * period), max(low_speed, 2.0), min(high_speed,
                                                                               settings.max_ptu_speed_deg_s)))
            driver.move_to(pan, tilt, speed_deg_s=speed)
            self._ptu_speed_deg_s = speed
        return f"{pan:.2f},{tilt:.2f}@{speed:.0f}"

    def _look_around(self, devices: Any, seen: Seen) -> str:
        """Lost: sweep the pan between the search's limits at the search tilt, the frames looking for
        a person all the while (the reacquisition), first towards where the target was last."""
        settings = self.settings
        if seen.sim_s - self._lost_s < settings.max_coast_s:
            # First where it was last: a walker gone out of range or behind a rock comes back there.
            return self._aim_at(devices, seen, self.track.position)
        low, high = settings.lost_sweep_pan_deg
        tilt = settings.search_tilt_deg.of(self.sensor)
        if self._sweep_to is None:
            last_bearing, _ = self.sight.bearing_range(seen.pose, self.track.position)
            self._sweep_to = high if last_bearing >= seen.pan_deg else low
        elif abs(seen.pan_deg - self._sweep_to) <= settings.deadband_deg:
            self._sweep_to = low if self._sweep_to == high else high
        with devices.sharing.borrow("ptu") as busy:
            if busy is not None:
                return "busy"
            driver = devices.ptu.ready_driver()
            driver.move_to(self._sweep_to, tilt, speed_deg_s=settings.lost_sweep_speed_deg_s)
            self._ptu_speed_deg_s = settings.lost_sweep_speed_deg_s
        return f"sweep {self._sweep_to:.0f},{tilt:.0f}@{settings.lost_sweep_speed_deg_s:.0f}"

    def _record(self, seq: int, seen: Seen, chosen: Candidate | None, count: int, command: str) -> TrackRecord:
        track = self.track
        x, y = track.position
        vx, vy = track.velocity
        bearing, range_m = self.sight.bearing_range(seen.pose, track.position)
        sigma = float(math.sqrt(max(track.covariance[0, 0], track.covariance[1, 1])))
        state = "tracking" if self.locked else "lost"
        return TrackRecord(seq, seen.sim_s, state, chosen is not None, float(x), float(y),
                           self.ground_z, float(vx), float(vy), sigma, range_m, bearing,
                           chosen.confidence if chosen is not None else math.nan, seen.pan_deg, seen.tilt_deg,
                           command, seen.grab_ms, seen.process_ms, count, truth=seen.truth,
                           measured=None if chosen is None else (chosen.shape.x, chosen.shape.y,
                                                                 chosen.shape.ground_z, chosen.shape.height))

    def unknown(self, seq: int, reason: str) -> dict[str, Any]:
        record = TrackRecord(seq, self.server.clock.now(), "unknown", False, math.nan, math.nan, math.nan, math.nan,
                             math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, "", math.nan,
                             math.nan, 0, reason=reason)
        self.records.append(record)
        return record.event()

    def _keep_for_picture(self, seen: Seen) -> None:
        self._picture_count += 1
        if self._picture_count % max(1, int(self.rate_hz)) == 1 or len(self._picture) == 0:
            step = max(1, len(seen.points) // 4000)
            if sum(len(p) for p in self._picture) < PICTURE_POINTS:
                self._picture.append(seen.points[::step])

    # -- the end -----------------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        records = self.records
        frames = len(records)
        tracking = [r for r in records if r.state == "tracking"]
        errors = [math.hypot(r.x - r.truth["x"], r.y - r.truth["y"]) for r in tracking
                  if r.truth and r.truth.get("visible", 0) > 0]
        measured = [r.process_ms for r in records if r.state != "unknown"]
        return {"frames": frames, "tracked": f"{len(tracking) / frames:.3f}" if frames else "0",
                "measured": sum(r.seen for r in records), "lost": sum(r.state == "lost" for r in records),
                "unknown": sum(r.state == "unknown" for r in records),
                "rate_hz": round(self.measured_rate(), 2),
                "process_ms_p50": round(float(np.percentile(measured, 50)), 1) if measured else None,
                "process_ms_p95": round(float(np.percentile(measured, 95)), 1) if measured else None,
                "rmse_m": float(np.sqrt(np.mean(np.square(errors)))) if errors else None,
                "sensor": self.sensor}

    def finish(self) -> dict[str, Any]:
        devices = self.server.devices
        devices.sharing.unclaim("ptu", self.kind)
        with devices.sharing.borrow(self.sight.frames.device) as busy:
            if busy is None:       # a job that holds it took the camera's own settings back already
                self.sight.frames.release(devices)
        summary = self.summary()
        points = np.concatenate(self._picture) if self._picture else np.zeros((0, 3))
        write_track(self.product, self.records, points, self.sensor_xy, summary)
        self.product.note("summary", summary)
        self.product.finish()
        self.server.publish_threadsafe("product", {"name": self.product.name, "command": "track3d-start",
                                                   "path": str(self.product.path)})
        return {"activity": "track", "frames": summary["frames"], "tracked": summary["tracked"],
                "rate": f"{self.measured_rate():.2f}", "product": self.product.name, "path": str(self.product.path)}
