"""track3d-detect's search: sweep the pan, two tilts per pan (one that sees a person's head from
about 2.3 m, one lower that sees the ground at its feet), every frame into one world cloud; then the
ground taken away, what stands on it clustered and judged by its shape (toolbox/tracking)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from rvs_server.devices.frame_points import SENSOR_DEVICE
from toolbox.tracking.detect import candidates

from .record import Judged
from .settings import TrackingSettings
from .sight import Seen, Sight

if TYPE_CHECKING:
    from rvs_server.jobs import JobContext


BODY_M = 0.5      # two sightings this close are one person whenever they were taken


@dataclass(frozen=True)
class Search:
    views: list[Seen]
    judged: list[Judged]          # every standing cluster, most person-like first

    @property
    def people(self) -> list[Judged]:
        return [j for j in self.judged if j.person]

    @property
    def points(self) -> np.ndarray:
        return np.concatenate([v.points for v in self.views]) if self.views else np.zeros((0, 3))

    @property
    def sensor_xy(self) -> np.ndarray:
        return np.mean([v.sensor_xy for v in self.views], axis=0)


def search_pans(pan_range: tuple[float, float], step: float) -> list[float]:
    """Pans from one end of the range to the other, no more than `step` apart (one view for a
    range narrower than a step)."""
    low, high = pan_range
    count = max(1, int(math.ceil((high - low) / step - 1e-9)) + 1) if high > low else 1
    return [float(p) for p in np.linspace(low, high, count)] if count > 1 else [(low + high) / 2]


def sweep(ctx: JobContext, sight: Sight, settings: TrackingSettings, pan_range: tuple[float, float]) -> Search:
    sensor = sight.sensor
    devices = ctx.devices
    ptu = devices.ptu.require()
    devices[SENSOR_DEVICE[sensor]].require()
    speed = ctx.settings_of("ptu").default_speed_deg_s
    pans = search_pans(pan_range, settings.search_step_deg.of(sensor))
    tilts = (settings.search_tilt_deg.of(sensor), settings.ground_tilt_deg.of(sensor))
    looks = [(pan, tilt) for pan in pans for tilt in (tilts if pans.index(pan) % 2 == 0 else tilts[::-1])]
    views = []
    for index, (pan, tilt) in enumerate(looks):
        ctx.safe_point()
        ctx.progress(5 + 80 * index / len(looks), f"view {index + 1} of {len(looks)}: pan {pan:.0f} tilt {tilt:.0f}")
        ptu.move_to(pan, tilt, speed_deg_s=speed)
        ptu.wait_until_stopped(timeout_s=120.0)
        views.append(sight.seen(sight.grab(devices)))
    ctx.progress(88, "finding what stands on the ground")
    return judge(views, sight, settings)


def judge(views: list[Seen], sight: Sight, settings: TrackingSettings) -> Search:
    """Every view judged on its own (a walker is somewhere else in each, so one cloud of all would
    smear it), the rover's plane standing in for ground a view did not see; then what two views saw
    of one thing made one."""
    judged = []
    pose = views[0].pose if views else None
    params, model = settings.standing(sight.sensor), settings.person(sight.sensor)
    for view in views:
        for candidate in candidates(view.points, view.sensor_xy, view.plane, params, model):
            bearing, range_m = sight.bearing_range(pose, candidate.xy)
            judged.append(Judged(candidate, range_m, bearing, candidate.confidence >= settings.found_confidence,
                                 seen_s=view.sim_s))
    return Search(views, one_per_thing(judged, settings.walk_speed_m_s))


def one_per_thing(judged: list[Judged], speed: float) -> list[Judged]:
    """One entry per person and per thing the views saw. A person who walks while the sweep turns is
    seen again in a later view somewhere else: two sightings no farther apart than a walker gets
    between their views (plus a body) are one person, its latest sighting standing for it (where it
    is now). Anything else seen within a body of a person, or of a bigger cluster, is a view of that
    (cut by the edge of a view, or the same boulder twice). The repeats are kept, marked."""
    def near(a: Judged, b: Judged, moving: bool) -> bool:
        reach = BODY_M + (speed * abs(a.seen_s - b.seen_s) if moving else 0.0)
        return bool(np.linalg.norm(a.candidate.xy - b.candidate.xy) <= reach)

    people: list[Judged] = []
    repeats: list[Judged] = []
    for j in sorted((j for j in judged if j.person), key=lambda j: -j.seen_s):
        (repeats if any(near(j, k, True) for k in people) else people).append(j)
    things: list[Judged] = []
    for j in sorted((j for j in judged if not j.person), key=lambda j: -j.candidate.shape.points):
        if any(near(j, k, True) for k in people) or any(near(j, k, False) for k in things):
            repeats.append(j)
        else:
            things.append(j)
    return (sorted(people, key=lambda j: j.range_m) + things
            + [replace(j, person=False, repeated=True) for j in repeats])
