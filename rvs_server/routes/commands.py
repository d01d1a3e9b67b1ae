"""Image-based routes (seeds/image-based-route-maps.txt): teach a route, repeat it, join routes.

    drive --forward M | --backward M | --turn DEG      one action; while a route is being recorded,
                                                       also a triplet (image before, action, image after)
    route-record start --name NAME | stop              short-term memory, then long-term (the store)
    route-follow --name NAME [--reverse] [--matcher M] repeat a route (toolbox/routes_follow.py)
    route-connect [--matcher M]                        link places of different routes that look alike
    route-list                                         the routes, their size and their links
    route-go --to NAME:INDEX [--matcher M]             from wherever the rover is, through the network
    sun --azimuth DEG --elevation DEG                  simulated: move the sun (shadows, brightness)

Routes live in an SQLite database in the data directory (rvs_server/routes/store.py: images
compressed, every matcher's descriptors beside them), so they survive a restart. The matcher
("features", the default, or the paper's "contour") is chosen per command; both describe every
image when it is stored.
"""
from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from rvs_server.config import CommandConfig, SafeName, Settings
from rvs_server.devices import ForwardCameraConfig
from rvs_server.devices.rover import action_motion
from rvs_server.dispatch import Call, Module
from rvs_server.host import Host
from rvs_server.jobs import JobContext
from rvs_server.products.canvas import sheet
from rvs_server.products.rasters import write_png
from rvs_server.protocol import BadRequest, WrongMode
from rvs_server.routes.rover import RouteRover, check_rover
from rvs_server.routes.store import Action, RouteStore, RouteStoreConfig, RouteStoreError
from toolbox.colour import with_title
from toolbox.routes.follow import FollowParams, FollowReport, Leg, RouteFollower
from toolbox.routes.match import MATCHER_NAMES, rank_route
from toolbox.routes.network import NetworkLeg, NetworkLink, Segment, shortest_way

Matcher = Literal["features", "contour"]


class FollowSettings(Settings):
    """toolbox/routes_follow.py FollowParams."""

    blind_fraction: float = Field(0.8, ge=0, le=1, description="of a drive made before looking for its image after")
    scene_depth_m: float = Field(4.0, gt=0, description="typical depth of matched features: scale error to distance")
    scale_tolerance: float = Field(0.03, gt=0, le=0.5, description="arrived when |scale - 1| is below this")
    min_step_m: float = Field(0.03, gt=0)
    max_step_m: float = Field(0.4, gt=0)
    search_step_fraction: float = Field(0.1, gt=0, le=1)
    overshoot: float = Field(0.5, ge=0, le=3, description="a drive goes on at most this fraction of its length "
                             "beyond it looking for its image after")
    heading_tolerance_deg: float = Field(1.0, gt=0)
    max_heading_corrections: int = Field(3, ge=0, le=20)
    max_approach_steps: int = Field(10, ge=0, le=100)
    recovery_window: int = Field(3, ge=0, le=50)
    scan_deg: tuple[float, ...] = Field((8.0, -8.0, 16.0, -16.0), description="headings, relative to the turn's "
                                        "end, looked at when a turn's image after is not seen")
    backing_gain: float = Field(2.0, ge=0, le=10, description="backing up, the parallax of a sideways offset (near "
                                "minus far points' shift) turns the rear back onto the path this strongly")


class RoutesSettings(Settings):
    matcher: Matcher = Field("features", description="default matcher: features (ORB on CLAHE, RANSAC) or the "
                             "paper's contour matcher")
    camera: Literal["forward", "left"] = Field("forward", description="forward: the simulated body-fixed camera; "
                                               "left: the left stereo camera at pan 0")
    left_tilt_deg: float = Field(-20.0, ge=-90, le=30)
    image_width: int = Field(640, ge=64, le=4096, description="route images are this wide (camera left)")
    forward_camera: ForwardCameraConfig = ForwardCameraConfig()
    actions: Literal["auto", "simulated", "gnc"] = Field("auto", description="who executes actions: the simulated "
                                                       "rover, or the GNC (navigate event, then pose)")
    truth_step_m: float = Field(0.10, gt=0, description="simulated: rocks taller than this count as contacts")
    max_drive_m: float = Field(20.0, gt=0, le=100, description="longest single drive action")
    pose_timeout_s: float = Field(300.0, gt=0)
    image_format: Literal["webp", "png"] = "webp"
    webp_quality: int = Field(90, ge=1, le=101)
    image_downscale: int = Field(1, ge=1, le=16)
    follow: FollowSettings = FollowSettings()
    orient: bool = Field(False, description="simulated drives: a drive leg is made in parts of at most "
                         "orient_step_m with an orient look after each, each part aimed back at the leg's line "
                         "from where the look put the rover (the wheels' drift taken out within the leg)")
    orient_sensor: Literal["stereo", "tof"] = Field("tof", description="the sensor those looks take")
    orient_step_m: float = Field(1.0, gt=0.1, le=5.0, description="longest part of a drive leg between two looks")
    connect_window: int = Field(2, ge=0, le=20, description="route-connect keeps a link only where it is the "
                                "best match within this many places along both routes")
    turn_cost_m: float = Field(0.3, ge=0, description="route-go: a radian of turning costs this many metres")
    link_cost_m: float = Field(0.5, ge=0, description="route-go: crossing a link costs this many metres")

    def store_config(self) -> RouteStoreConfig:
        return RouteStoreConfig(image_format=self.image_format, webp_quality=self.webp_quality,
                                image_downscale=self.image_downscale, matchers=MATCHER_NAMES)

    def follow_params(self) -> FollowParams:
        return FollowParams(**self.follow.model_dump())


module = Module("routes", settings=RoutesSettings, summary="image-based routes: record, follow, connect, go",
                state=lambda server: RoutesState(server))


# ------------------------------------------------------------------------------------ state
class RoutesState:
    """The store of one server, and the recording in progress (the paper's short-term memory)."""

    def __init__(self, server: Host):
        self.store = RouteStore(server.data_dir / "routes", _settings(server).store_config())
        self.before: int | None = None          # image id the next recorded action starts from
        self.true_path: list[list[float]] = []  # simulated: the taught route as driven

    def recording(self) -> str | None:
        return next((r.name for r in self.store.list_routes() if r.state == "recording"), None)


def state_of(server: Host) -> RoutesState:
    return server.state_of("routes")


def _settings(server: Host) -> RoutesSettings:
    return server.settings_of("routes")


def _check(server: Host, cfg: Any = None) -> None:
    check_rover(server, _settings(server))


def _pose_tuple(server: Host) -> tuple[float, float, float]:
    pose = server.devices.rover.pose_estimate
    return (pose.x, pose.y, pose.heading)


# ------------------------------------------------------------------------------------ drive
class DriveConfig(CommandConfig):
    forward: float | None = Field(None, gt=0, description="drive forward this far, metres")
    backward: float | None = Field(None, gt=0, description="drive backward this far, metres")
    turn: float | None = Field(None, ge=-180, le=180, description="turn on the spot, degrees counter-clockwise")
    unguarded: bool = Field(False, description="with hazard detection running, turn or back up over ground "
                            "no frame saw (a remembered hazard still refuses it)")

    @model_validator(mode="after")
    def _one_action(self) -> DriveConfig:
        given = [name for name in ("forward", "backward", "turn") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of --forward M, --backward M, --turn DEG (got "
                             f"{', '.join('--' + g for g in given) or 'none'})")
        if self.turn == 0:
            raise ValueError("--turn = 0: a turn of nothing is no action; allowed: -180..180, not 0")
        return self

    def action(self) -> Action:
        if self.turn is not None:
            return Action("turn", math.radians(self.turn))
        return Action("forward", self.forward) if self.forward is not None else Action("backward", self.backward)


def _validate_drive(server: Host, cfg: DriveConfig) -> None:
    settings = _settings(server)
    distance = cfg.forward or cfg.backward or 0.0
    if distance > settings.max_drive_m:
        raise BadRequest(f"drive: {distance:g} m is longer than routes.toml max_drive_m ({settings.max_drive_m:g} m)")
    _check(server)


@module.job("drive", DriveConfig, resumable=False, validate=_validate_drive)
def drive(ctx: JobContext, cfg: DriveConfig) -> dict[str, Any]:
    """One action; while a route is recorded, its triplet (image before, action, image after) too."""
    state, settings = ctx.state, ctx.settings
    route = state.recording()
    action = cfg.action()
    rover = RouteRover(ctx, settings)
    before = None
    if route is not None:
        before = state.before
        if before is None:   # a restart lost the short-term memory's last image: look again
            before = state.store.add_image(route, rover.grab(), _pose_tuple(ctx.server))
    shown = f"{math.degrees(action.value):g} deg" if action.kind == "turn" else f"{action.value:g} m"
    said = _swept_by_guard(ctx, action, cfg.unguarded)
    ctx.progress(10, f"{action.kind} {shown}")
    rover.act(action.kind, action.value)
    reply: dict[str, Any] = {"action": action.kind, "value": cfg.turn if action.kind == "turn" else action.value,
                             **said}
    if route is not None:
        ctx.progress(80, f"recording: the image after, into route {route}")
        after = state.store.add_image(route, rover.grab(), _pose_tuple(ctx.server))
        triplet = state.store.add_triplet(route, before, action, after)
        state.before = after
        state.true_path.extend(rover.true_path[1:])
        reply.update({"route": route, "triplet": triplet.index})
    pose = ctx.devices.rover.pose_estimate
    return {**reply, "x": f"{pose.x:.3f}", "y": f"{pose.y:.3f}", "heading": f"{math.degrees(pose.heading):.2f}"}


def _swept_by_guard(ctx: JobContext, action: Action, unguarded: bool) -> dict[str, Any]:
    """A turn on the spot or a backward drive asks the drive guard (hazard-start) first: refused by
    name (400) when it would sweep a remembered hazard or, unless --unguarded, unseen ground."""
    guard = ctx.devices.rover.guard
    if guard is None or action.kind == "forward":
        return {}
    turn, distance = action_motion(action.kind, action.value)
    sentence, said = guard.swept(ctx, ctx.devices.rover.pose_estimate, turn, distance, unguarded)
    if sentence is not None:
        raise BadRequest(f"drive refused: {guard.name}: {sentence}")
    return said


# ------------------------------------------------------------------------------------ route-record
class RecordConfig(CommandConfig):
    action: Literal["start", "stop"] = Field(..., description="start: begin a route (needs --name); stop: keep it")
    name: SafeName | None = Field(None, description="the new route's name")


def _validate_record(server: Host, cfg: RecordConfig) -> None:
    state = state_of(server)
    recording = state.recording()
    if cfg.action == "start":
        if cfg.name is None:
            raise BadRequest("route-record start: --name NAME is required")
        if recording is not None:
            raise WrongMode(f"route-record start: route {recording!r} is being recorded; route-record stop first")
        if any(r.name == cfg.name for r in state.store.list_routes()):
            raise BadRequest(f"route-record start: --name = {cfg.name!r}: a route of that name exists; choose another")
        _check(server)
    elif recording is None:
        raise WrongMode("route-record stop: no route is being recorded")
    elif cfg.name is not None and cfg.name != recording:
        raise BadRequest(f"route-record stop: --name = {cfg.name!r}, but the route being recorded is {recording!r}")
    elif not state.store.triplets(recording):
        # A route of no action has no places to sheet or follow (was a 500 from its contact sheet).
        raise WrongMode(f"route-record stop: route {recording!r} has no action yet; drive first (it is still "
                        "being recorded)")


@module.job("route-record", RecordConfig, resumable=False, validate=_validate_record, positionals=("action",))
def route_record(ctx: JobContext, cfg: RecordConfig) -> dict[str, Any]:
    """Start recording a route (its first image), or stop and keep it in long-term memory."""
    state, store = ctx.state, ctx.state.store
    if cfg.action == "start":
        rover = RouteRover(ctx, ctx.settings)
        store.create_route(cfg.name, metadata={"camera": ctx.settings.camera})
        ctx.progress(50, f"route {cfg.name}: the first image")
        state.before = store.add_image(cfg.name, rover.grab(), _pose_tuple(ctx.server))
        state.true_path = rover.true_path[:1]
        return {"route": cfg.name, "state": "recording"}
    route = state.recording()
    summary = store.finish_route(route)
    report = store.storage_report(route)
    product = ctx.product(cfg, name=f"route-{route}")
    triplets = store.triplets(route)
    places = [t.image_before for t in triplets] + ([triplets[-1].image_after] if triplets else [])
    write_png(product.add("places.png", "contact sheet: every place of the route, in order"),
              with_title(contact_sheet([store.image(i) for i in places]), f"route {route}: {len(places)} places"))
    product.write_json("route.json", {"route": route, "triplets": [
        {"index": t.index, "action": t.action.kind, "value": t.action.value, "image_before": t.image_before,
         "image_after": t.image_after, "pose_before": store.image_record(t.image_before).pose} for t in triplets],
        "storage": {**asdict(report), "bytes_per_metre": report.bytes_per_metre}},
        "the route's triplets (values: metres, or radians CCW for turns), estimated poses, bytes stored")
    if ctx.devices.simulated and state.true_path:
        product.write_json("truth/path.json", {"path": state.true_path},
                           "the route as truly driven while taught: x, y, heading (rad) every 5 cm")
    state.before, state.true_path = None, []
    result = ctx.finish_product(product)
    per_metre = report.bytes_per_metre
    return {**result, "route": route, "triplets": summary.triplets, "length": f"{summary.length_m:.2f}",
            "bytes": report.bytes_total, "bytes_per_m": "" if per_metre is None else f"{per_metre:.0f}"}


def contact_sheet(images: list[np.ndarray], columns: int = 6, width: int = 200) -> np.ndarray:
    tiles = []
    for number, image in enumerate(images):
        tile = cv2.resize(image, (width, round(image.shape[0] * width / image.shape[1])), interpolation=cv2.INTER_AREA)
        tile = cv2.cvtColor(tile, cv2.COLOR_GRAY2RGB)
        cv2.putText(tile, str(number), (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 220, 0), 2, cv2.LINE_AA)
        tiles.append(tile)
    return sheet(tiles, columns, fill=0)


# ------------------------------------------------------------------------------------ route-follow
class FollowConfig(CommandConfig):
    name: SafeName = Field(..., description="the route to repeat")
    reverse: bool = Field(False, description="repeat it backward, from its end to its start")
    matcher: Matcher | None = Field(None, description="features or contour; default routes.toml")
    output: SafeName | None = None


def _validate_follow(server: Host, cfg: FollowConfig) -> None:
    state = state_of(server)
    _finished_route(state, cfg.name, "route-follow")
    _check(server)


def _finished_route(state: RoutesState, name: str, command: str) -> None:
    try:
        summary = state.store.route(name)
    except RouteStoreError:
        known = ", ".join(r.name for r in state.store.list_routes()) or "none"
        raise BadRequest(f"{command}: --name = {name!r}: no such route; known: {known}") from None
    if summary.state != "finished":
        raise WrongMode(f"{command}: route {name!r} is still being recorded; route-record stop first")
    if summary.triplets == 0:
        raise BadRequest(f"{command}: route {name!r} has no triplets")


@module.job("route-follow", FollowConfig, resumable=False, validate=_validate_follow)
def route_follow(ctx: JobContext, cfg: FollowConfig) -> dict[str, Any]:
    """Repeat a route: each action stopped when the live view matches its image after."""
    matcher_name = cfg.matcher or ctx.settings.matcher
    last = len(ctx.state.store.triplets(cfg.name))   # the last place
    segment = Segment(cfg.name, last, 0) if cfg.reverse else Segment(cfg.name, 0, last)
    product = ctx.product(cfg, name=cfg.output)
    run = FollowRun(ctx, matcher_name, product)
    report = run.follow(segment, 0, 1)
    return run.finish([report], [segment])


class FollowRun:
    """One job's following: the rover, the matcher, progress, and the product at the end."""

    def __init__(self, ctx: JobContext, matcher_name: str, product: Any):
        self.ctx, self.product = ctx, product
        self.state = ctx.state
        self.matcher_name = matcher_name
        self.matcher = self.state.store.matcher(matcher_name)
        self.rover = RouteRover(ctx, ctx.settings, self.matcher)
        self.params = ctx.settings.follow_params()

    def legs(self, segment: Segment) -> list[Leg]:
        loaded = self.state.store.load_route(segment.route, self.matcher_name, reverse=segment.reverse)
        triplets = loaded.triplets
        n = len(triplets)
        first, last = (n - segment.start, n - segment.end) if segment.reverse else (segment.start, segment.end)
        d = loaded.descriptors
        return [Leg(d[t.image_before], t.action.kind, t.action.value, d[t.image_after]) for t in triplets[first:last]]

    def follow(self, segment: Segment, number: int, total: int) -> FollowReport:
        legs = self.legs(segment)

        def progress(done: int, count: int, message: str) -> None:
            percent = 100.0 * (number + done / max(count, 1)) / total
            self.ctx.progress(min(99.0, percent),
                              f"{segment.route}{' (reverse)' if segment.reverse else ''}: {message}")

        return RouteFollower(legs, self.matcher, self.rover, self.params, progress).run()

    def finish(self, reports: list[FollowReport], segments: list[Segment]) -> dict[str, Any]:
        ctx, product = self.ctx, self.product
        success = all(r.success for r in reports)
        looks = self.rover.orient_looks
        document = {"matcher": self.matcher_name, "success": success, "images": self.rover.images,
                    "orient_looks": len(looks),
                    "orient_refused": [f"{look['failed']}: {look['sentence']}" for look in looks if look["failed"]],
                    "segments": [{**asdict(s), "reverse": s.reverse, "success": r.success, "reason": r.reason,
                                  "last_matched": r.last_matched, "legs": [asdict(leg) for leg in r.legs]}
                                 for s, r in zip(segments, reports, strict=True)]}
        product.write_json("follow.json", document, "per segment and leg: matched, similarity, approach steps, "
                           "heading corrections, metres travelled, recovery")
        if ctx.devices.simulated:
            product.write_json("truth/path.json", {"path": self.rover.true_path},
                               "the repeat as truly driven: x, y, heading (rad) every 5 cm")
        result = ctx.finish_product(product)
        failed = next((r for r in reports if not r.success), None)
        legs = sum(len(r.legs) for r in reports)
        if failed is not None:
            segment = segments[reports.index(failed)]
            raise BadRequest(f"route lost on {segment.route}: {failed.message}; product={product.name}",
                             data={"product": product.name, "reason": failed.reason, "route": segment.route,
                                   "last_matched": failed.last_matched})
        return {**result, "legs": legs, "images": self.rover.images, "matcher": self.matcher_name}


# ------------------------------------------------------------------------------------ route-connect
class ConnectConfig(CommandConfig):
    matcher: Matcher | None = Field(None, description="features or contour; default routes.toml")


def _validate_connect(server: Host, cfg: ConnectConfig) -> None:
    finished = [r for r in state_of(server).store.list_routes() if r.state == "finished"]
    if len(finished) < 2:
        raise WrongMode(f"route-connect: needs two finished routes, there are {len(finished)}")


@module.job("route-connect", ConnectConfig, resumable=False, validate=_validate_connect)
def route_connect(ctx: JobContext, cfg: ConnectConfig) -> dict[str, Any]:
    """Link places of different routes that look alike (sec. 3.4): the best match in its neighbourhood."""
    store = ctx.state.store
    matcher_name = cfg.matcher or ctx.settings.matcher
    matcher = store.matcher(matcher_name)
    routes = [r.name for r in store.list_routes() if r.state == "finished"
              and "reversed_from" not in r.metadata]
    existing = {(k.route_a, k.index_a, k.route_b, k.index_b) for k in store.links()}
    places = {name: place_descriptors(store, name, matcher_name) for name in routes}
    added, pairs = [], [(a, b) for i, a in enumerate(routes) for b in routes[i + 1:]]
    for number, (a, b) in enumerate(pairs):
        ctx.progress(100.0 * number / len(pairs), f"matching {a} against {b}")
        for ia, ib, similarity in linked_places(matcher, places[a], places[b], ctx.settings.connect_window):
            if (a, ia, b, ib) in existing or (b, ib, a, ia) in existing:
                continue
            store.add_link(a, ia, b, ib, similarity)
            added.append({"a": f"{a}:{ia}", "b": f"{b}:{ib}", "similarity": round(similarity, 3)})
    return {"links": len(added), "pairs": len(pairs), "matcher": matcher_name,
            "added": " ".join(f"{x['a']}={x['b']}" for x in added)}


def place_descriptors(store: RouteStore, route: str, matcher: str) -> list[Any]:
    loaded = store.load_route(route, matcher)
    return [loaded.descriptors[i] for i in loaded.place_images()]


def linked_places(matcher: Any, a: list[Any], b: list[Any], window: int) -> list[tuple[int, int, float]]:
    """(index in a, index in b, similarity) of places that match, each the best within `window`
    places along both routes (a stretch of shared way gives its best pairs, not every pair)."""
    score = np.zeros((len(a), len(b)))
    for i, da in enumerate(a):
        for j, result in ((r.index, r.result) for r in rank_route(matcher, da, b)):
            if result.same_place:
                score[i, j] = result.similarity
    links = []
    for i, j in zip(*np.nonzero(score), strict=True):
        around = score[max(0, i - window):i + window + 1, max(0, j - window):j + window + 1]
        if score[i, j] >= around.max():
            links.append((int(i), int(j), float(score[i, j])))
    return links


# ------------------------------------------------------------------------------------ route-list
@module.command("route-list", CommandConfig)
def route_list(call: Call, cfg: CommandConfig) -> dict[str, Any]:
    """The routes: state, legs, length, bytes stored, links."""
    store = call.state.store
    routes = store.list_routes()
    links = store.links()
    reply: dict[str, Any] = {"count": len(routes)}
    for r in routes:
        count = sum(1 for k in links if r.name in (k.route_a, k.route_b))
        reply[f"route.{r.name}"] = (f"{r.state} legs={r.triplets} length={r.length_m:.2f}m "
                                    f"bytes={r.image_bytes + r.descriptor_bytes} links={count}")
    reply["links"] = " ".join(f"{k.route_a}:{k.index_a}={k.route_b}:{k.index_b}" for k in links)
    return reply


# ------------------------------------------------------------------------------------ route-go
class GoConfig(CommandConfig):
    to: str = Field(..., description="NAME:INDEX, a place of a route (0 is its start)")
    matcher: Matcher | None = Field(None, description="features or contour; default routes.toml")
    output: SafeName | None = None


def _parse_place(state: RoutesState, text: str) -> tuple[str, int]:
    name, _, index = text.rpartition(":")
    try:
        number = int(index)
    except ValueError:
        number = -1
    if not name or number < 0:
        raise BadRequest(f"route-go: --to = {text!r}: expected NAME:INDEX, INDEX a place number >= 0")
    _finished_route(state, name, "route-go")
    places = len(state.store.triplets(name)) + 1
    if number >= places:
        raise BadRequest(f"route-go: --to = {text!r}: route {name!r} has places 0..{places - 1}")
    return name, number


def _validate_go(server: Host, cfg: GoConfig) -> None:
    _parse_place(state_of(server), cfg.to)
    _check(server)


@module.job("route-go", GoConfig, resumable=False, validate=_validate_go)
def route_go(ctx: JobContext, cfg: GoConfig) -> dict[str, Any]:
    """Find where the rover is on the route network, then follow the shortest way to the place."""
    state, store = ctx.state, ctx.state.store
    goal = _parse_place(state, cfg.to)
    matcher_name = cfg.matcher or ctx.settings.matcher
    product = ctx.product(cfg, name=cfg.output)
    run = FollowRun(ctx, matcher_name, product)
    ctx.progress(2, "where am I: matching the live view against every place of every route")
    start = locate(store, run, matcher_name)
    if start is None:
        result = ctx.finish_product(product)
        raise BadRequest(f"route-go: lost_at_start: the live view matches no place of any route; "
                         f"product={result['product']}", data={"product": result["product"],
                                                              "reason": "lost_at_start"})
    routes = [r.name for r in store.list_routes() if r.state == "finished" and "reversed_from" not in r.metadata]
    legs = [NetworkLeg(r, t.index, t.action.kind, t.action.value) for r in routes for t in store.triplets(r)]
    links = [NetworkLink((k.route_a, k.index_a), (k.route_b, k.index_b)) for k in store.links()]
    way = shortest_way(legs, links, start, goal, ctx.settings.turn_cost_m, ctx.settings.link_cost_m)
    if way is None:
        raise BadRequest(f"route-go: no way from {start[0]}:{start[1]} to {cfg.to} through the route network "
                         f"(route-connect links routes where they meet); product={product.name}",
                         data={"product": product.name, "reason": "unconnected"})
    segments, cost = way
    product.write_json("way.json", {"from": list(start), "to": list(goal), "cost_m": cost,
                                    "segments": [{**asdict(s), "reverse": s.reverse} for s in segments]},
                       "the way through the route network: stretches of routes, in order")
    reports = []
    for number, segment in enumerate(segments):
        reports.append(run.follow(segment, number, len(segments)))
        if not reports[-1].success:
            break
    result = run.finish(reports, segments[:len(reports)])
    return {**result, "from": f"{start[0]}:{start[1]}", "segments": len(segments), "cost": f"{cost:.2f}"}


def locate(store: RouteStore, run: FollowRun, matcher_name: str) -> tuple[str, int] | None:
    """The place of any finished route the live view matches best, or None."""
    live = run.rover.look()
    best: tuple[float, tuple[str, int]] | None = None
    for summary in store.list_routes():
        if summary.state != "finished" or "reversed_from" in summary.metadata:
            continue
        ranked = rank_route(run.matcher, live, place_descriptors(store, summary.name, matcher_name), top=1)
        if ranked and ranked[0].result.same_place and (best is None or ranked[0].result.similarity > best[0]):
            best = (ranked[0].result.similarity, (summary.name, ranked[0].index))
    return None if best is None else best[1]
