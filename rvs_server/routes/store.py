"""The route store: image-based routes in an embedded SQLite database (one file in a directory).

A route (seeds/image-based-route-maps.txt, sec. 3.1) is a sequence of triplets: image before,
action, image after. While the rover records, the route is in the 'recording' state, the paper's
short-term memory; `finish_route` keeps the triplets that lie on the way found (all, by default) and
moves the route to 'finished', the long-term memory. Routes can be followed backward (sec. 3.2:
`reversed_triplets`, `reverse_route`) and connected where two of their places look alike
(sec. 3.4: `add_link`).

The paper names memory as the method's cost (sec. 4.3); here each image is stored once, grey,
compressed (WebP or PNG, optionally downscaled), and beside it every matcher's descriptor, computed
once from the full image when it is added, so following a route loads descriptors only and never
decodes an image. `storage_report` gives the bytes per image and per metre of route.

Tables (schema version 2; `MIGRATIONS` applies older databases' upgrades in order on open):
    schema_version(version)
    routes(id, name, created, state, matchers JSON, metadata JSON, finished)
    images(id, route_id, encoding, width, height, source_width, source_height, data,
           pose_x, pose_y, pose_heading, captured, metadata JSON)
    descriptors(image_id, matcher, data)             one row per image and matcher
    triplets(route_id, idx, image_before, action_kind, action_value, image_after)
    links(id, route_a, index_a, route_b, index_b, similarity, action_kind, action_value, created)

Places along a route are numbered 0..n for n triplets: place i is the image before triplet i, place
n the last image after. Actions: 'forward' / 'backward' by value metres (>= 0), 'turn' by value
radians, counter-clockwise positive like the rover's heading.

One `RouteStore` serialises its operations with a lock and may be shared by threads (one writer at
a time); the database runs in WAL mode, so other processes can read while it writes.
"""
from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rvs_server.protocol import check_safe_name
from toolbox.routes.match import MATCHER_NAMES, PlaceMatcher, grey_image, make_matcher

DATABASE_FILE = "routes.sqlite"
ACTION_KINDS = ("forward", "backward", "turn")

# Each migration is (version it leads to, what it does, statements); applied in order, each in
# one transaction with its version row, so a database is always at exactly one version.
MIGRATIONS: tuple[tuple[int, str, tuple[str, ...]], ...] = (
    (1, "routes, images, descriptors, triplets", (
        "CREATE TABLE schema_version (version INTEGER NOT NULL)",
        "INSERT INTO schema_version (version) VALUES (0)",
        """CREATE TABLE routes (
            id INTEGER PRIMARY KEY,
            name TEXT NOT NULL UNIQUE,
            created TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ('recording', 'finished')),
            matchers TEXT NOT NULL,
            metadata TEXT NOT NULL DEFAULT '{}')""",
        """CREATE TABLE images (
            id INTEGER PRIMARY KEY,
            route_id INTEGER REFERENCES routes(id),
            encoding TEXT NOT NULL CHECK (encoding IN ('png', 'webp')),
            width INTEGER NOT NULL,
            height INTEGER NOT NULL,
            source_width INTEGER NOT NULL,
            source_height INTEGER NOT NULL,
            data BLOB NOT NULL,
            pose_x REAL,
            pose_y REAL,
            pose_heading REAL,
            captured TEXT NOT NULL,
            metadata TEXT NOT NULL DEFAULT '{}')""",
        "CREATE INDEX images_by_route ON images(route_id)",
        """CREATE TABLE descriptors (
            image_id INTEGER NOT NULL REFERENCES images(id) ON DELETE CASCADE,
            matcher TEXT NOT NULL,
            data BLOB NOT NULL,
            PRIMARY KEY (image_id, matcher))""",
        """CREATE TABLE triplets (
            route_id INTEGER NOT NULL REFERENCES routes(id) ON DELETE CASCADE,
            idx INTEGER NOT NULL CHECK (idx >= 0),
            image_before INTEGER NOT NULL REFERENCES images(id),
            action_kind TEXT NOT NULL CHECK (action_kind IN ('forward', 'backward', 'turn')),
            action_value REAL NOT NULL,
            image_after INTEGER NOT NULL REFERENCES images(id),
            PRIMARY KEY (route_id, idx))""",
    )),
    (2, "route links (route-connect, sec. 3.4) and the time a route was finished", (
        "ALTER TABLE routes ADD COLUMN finished TEXT",
        """CREATE TABLE links (
            id INTEGER PRIMARY KEY,
            route_a INTEGER NOT NULL REFERENCES routes(id) ON DELETE CASCADE,
            index_a INTEGER NOT NULL CHECK (index_a >= 0),
            route_b INTEGER NOT NULL REFERENCES routes(id) ON DELETE CASCADE,
            index_b INTEGER NOT NULL CHECK (index_b >= 0),
            similarity REAL NOT NULL,
            action_kind TEXT CHECK (action_kind IN ('forward', 'backward', 'turn')),
            action_value REAL,
            created TEXT NOT NULL,
            UNIQUE (route_a, index_a, route_b, index_b))""",
        "CREATE INDEX triplets_by_image_before ON triplets(image_before)",
        "CREATE INDEX triplets_by_image_after ON triplets(image_after)",
    )),
)
SCHEMA_VERSION = MIGRATIONS[-1][0]


class RouteStoreError(ValueError):
    """A request the store refuses (unknown route, route not recording, bad index, ...)."""


class RouteStoreConfig(BaseModel):
    """How images are kept. Descriptors are always computed from the image as given."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    image_format: Literal["webp", "png"] = "webp"
    # WebP quality 1-100 (lossy); 101 is OpenCV's lossless WebP.
    webp_quality: int = Field(90, ge=1, le=101)
    png_compression: int = Field(9, ge=0, le=9)
    # Integer downscale of the stored image (1 = as captured).
    image_downscale: int = Field(1, ge=1, le=16)
    matchers: tuple[str, ...] = MATCHER_NAMES


# ---------------------------------------------------------------------------- records

@dataclass(frozen=True)
class Action:
    """What the rover does between two images: forward / backward metres, or turn radians (CCW +)."""

    kind: Literal["forward", "backward", "turn"]
    value: float

    def __post_init__(self):
        if self.kind not in ACTION_KINDS:
            raise ValueError(f"action kind must be one of {', '.join(ACTION_KINDS)}, got {self.kind!r}")
        if not np.isfinite(self.value):
            raise ValueError(f"action value must be finite, got {self.value!r}")
        if self.kind != "turn" and self.value < 0:
            raise ValueError(f"{self.kind} distance must be >= 0 m, got {self.value!r}")

    def reversed(self) -> Action:
        """The action that undoes this one with the camera still facing the same way (sec. 3.2)."""
        if self.kind == "turn":
            return Action("turn", -self.value)
        return Action("backward" if self.kind == "forward" else "forward", self.value)

    @property
    def distance_m(self) -> float:
        return self.value if self.kind != "turn" else 0.0


@dataclass(frozen=True)
class Triplet:
    """One leg of a route: image ids before and after, and the action between them."""

    index: int
    image_before: int
    action: Action
    image_after: int


@dataclass(frozen=True)
class RouteSummary:
    name: str
    state: Literal["recording", "finished"]
    created: str
    finished: str | None
    matchers: tuple[str, ...]
    metadata: dict
    triplets: int
    images: int
    image_bytes: int
    descriptor_bytes: int
    length_m: float


@dataclass(frozen=True)
class StoredImage:
    id: int
    encoding: str
    width: int
    height: int
    source_width: int
    source_height: int
    pose: tuple[float, float, float] | None
    captured: str
    metadata: dict
    nbytes: int


@dataclass(frozen=True)
class Link:
    """Two places on two routes that look alike (sec. 3.4), with the action from A's to B's if known."""

    id: int
    route_a: str
    index_a: int
    route_b: str
    index_b: int
    similarity: float
    action: Action | None
    created: str


@dataclass(frozen=True)
class StorageReport:
    route: str
    images: int
    image_bytes: int
    descriptor_bytes: dict[str, int]
    length_m: float

    @property
    def bytes_total(self) -> int:
        return self.image_bytes + sum(self.descriptor_bytes.values())

    @property
    def bytes_per_image(self) -> float:
        return self.bytes_total / self.images if self.images else 0.0

    @property
    def bytes_per_metre(self) -> float | None:
        return self.bytes_total / self.length_m if self.length_m > 0 else None


@dataclass(frozen=True)
class LoadedRoute:
    """A route ready to follow: triplets and one matcher's descriptors by image id; no pixels."""

    name: str
    matcher: str
    triplets: list[Triplet]
    descriptors: dict[int, object]

    def place_images(self) -> list[int]:
        """Image id of each place 0..n along the route."""
        if not self.triplets:
            return []
        return [t.image_before for t in self.triplets] + [self.triplets[-1].image_after]


def reverse_triplets(triplets: Sequence[Triplet]) -> list[Triplet]:
    """The way back (sec. 3.2): triplets in reverse order, actions reversed, before/after swapped."""
    return [Triplet(i, t.image_after, t.action.reversed(), t.image_before)
            for i, t in enumerate(reversed(triplets))]


# ---------------------------------------------------------------------------- the store

class RouteStore:
    """Routes in `<directory>/routes.sqlite`; see the module docstring."""

    def __init__(self, directory: str | Path, config: RouteStoreConfig | None = None,
                 matchers: Mapping[str, PlaceMatcher] | None = None):
        self.config = config or RouteStoreConfig()
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path = self.directory / DATABASE_FILE
        self._matchers: dict[str, PlaceMatcher] = dict(matchers or {})
        self._lock = threading.RLock()
        # Autocommit mode: transactions are explicit (`_transaction`), DDL included.
        self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        try:
            self._conn.execute("PRAGMA foreign_keys = ON")
            self._conn.execute("PRAGMA journal_mode = WAL")
            # Every transaction commits whole or not at all: a kill cannot break the file in WAL mode, and
            # with FULL (SQLite's default, stated so it stays) a commit that returned survives a power cut.
            self._conn.execute("PRAGMA synchronous = FULL")
            migrate(self._conn)
        except BaseException:
            self._conn.close()
            raise

    # -- lifetime ------------------------------------------------------------------------------
    @classmethod
    def open(cls, directory: str | Path, config: RouteStoreConfig | None = None) -> RouteStore:
        return cls(directory, config)

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> RouteStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def schema_version(self) -> int:
        with self._lock:
            return _schema_version(self._connection())

    def matcher(self, name: str) -> PlaceMatcher:
        """The matcher used for descriptors of that name (created with its defaults on first use).
        Describing runs under the store's lock: OpenCV detectors are not shared between threads."""
        with self._lock:
            if name not in self._matchers:
                self._matchers[name] = make_matcher(name)
            return self._matchers[name]

    # -- recording -----------------------------------------------------------------------------
    def create_route(self, name: str, matchers: Sequence[str] | None = None,
                     metadata: Mapping | None = None) -> RouteSummary:
        """A new route in the 'recording' state, described by `matchers` (default: the config's)."""
        check_safe_name(name)
        matchers = tuple(matchers or self.config.matchers)
        for matcher in matchers:
            self.matcher(matcher)                      # an unknown name fails here, before writing
        with self._transaction() as db:
            if db.execute("SELECT 1 FROM routes WHERE name = ?", (name,)).fetchone():
                raise RouteStoreError(f"route {name!r} already exists")
            db.execute("INSERT INTO routes (name, created, state, matchers, metadata) VALUES (?, ?, ?, ?, ?)",
                       (name, _now(), "recording", json.dumps(matchers), json.dumps(dict(metadata or {}))))
        return self.route(name)

    def add_image(self, route: str, image: np.ndarray, pose: tuple[float, float, float] | None = None,
                  metadata: Mapping | None = None) -> int:
        """Store an image of a recording route with its descriptors; return its id."""
        with self._lock:
            route_id, matchers = self._recording_route(route)
            prepared = self._prepare_image(image, matchers, pose, metadata)
            with self._transaction() as db:
                return self._insert_image(db, route_id, prepared)

    def add_triplet(self, route: str, before: int | np.ndarray | None, action: Action | tuple[str, float],
                    after: int | np.ndarray) -> Triplet:
        """Append a triplet to a recording route, atomically with any image given as an array.

        `before` and `after` are image ids of this route or images (stored now, without a pose;
        use add_image first to give one); `before` None means the previous triplet's image after
        (the usual chain).
        """
        action = action if isinstance(action, Action) else Action(*action)
        if after is None:
            raise RouteStoreError("the image after an action is required")
        with self._lock:
            route_id, matchers = self._recording_route(route)
            ends = [self._prepare_image(x, matchers) if isinstance(x, np.ndarray) else x for x in (before, after)]
            with self._transaction() as db:
                before_id, after_id = (self._image_id(db, route, route_id, x) for x in ends)
                index = db.execute("SELECT COUNT(*) FROM triplets WHERE route_id = ?", (route_id,)).fetchone()[0]
                db.execute("INSERT INTO triplets VALUES (?, ?, ?, ?, ?, ?)",
                           (route_id, index, before_id, action.kind, float(action.value), after_id))
        return Triplet(index, before_id, action, after_id)

    def finish_route(self, route: str, keep: Sequence[int] | None = None) -> RouteSummary:
        """Short-term to long-term memory (sec. 3.1): keep the triplets `keep` (indices, in route
        order; default all), renumber them, drop images no longer used, and mark the route finished."""
        with self._lock:
            route_id, _ = self._recording_route(route)
            with self._transaction() as db:
                count = db.execute("SELECT COUNT(*) FROM triplets WHERE route_id = ?", (route_id,)).fetchone()[0]
                keep = list(range(count)) if keep is None else [int(k) for k in keep]
                if any(k < 0 or k >= count for k in keep) or keep != sorted(set(keep)):
                    raise RouteStoreError(f"keep must be increasing triplet indices of {route!r} "
                                          f"(0..{count - 1}), got {keep}")
                _renumber_triplets(db, route_id, keep)
                _delete_unused_images(db, route_id)
                db.execute("UPDATE routes SET state = 'finished', finished = ? WHERE id = ?", (_now(), route_id))
        return self.route(route)

    # -- reading -------------------------------------------------------------------------------
    def list_routes(self) -> list[RouteSummary]:
        with self._lock:
            names = [r[0] for r in self._connection().execute("SELECT name FROM routes ORDER BY name")]
            return [self.route(name) for name in names]

    def route(self, name: str) -> RouteSummary:
        """A route's state, matchers, counts, bytes and length."""
        with self._lock:
            db = self._connection()
            route_id = self._route_id(name)
            row = db.execute("SELECT state, created, finished, matchers, metadata FROM routes WHERE id = ?",
                             (route_id,)).fetchone()
            triplets, length = db.execute(
                "SELECT COUNT(*), COALESCE(SUM(CASE WHEN action_kind = 'turn' THEN 0 ELSE action_value END), 0) "
                "FROM triplets WHERE route_id = ?", (route_id,)).fetchone()
            images, image_bytes = db.execute(
                "SELECT COUNT(*), COALESCE(SUM(LENGTH(data)), 0) FROM images WHERE route_id = ?",
                (route_id,)).fetchone()
            descriptor_bytes = db.execute(
                "SELECT COALESCE(SUM(LENGTH(d.data)), 0) FROM descriptors d JOIN images i ON i.id = d.image_id "
                "WHERE i.route_id = ?", (route_id,)).fetchone()[0]
        return RouteSummary(name, row[0], row[1], row[2], tuple(json.loads(row[3])), json.loads(row[4]),
                            triplets, images, image_bytes, descriptor_bytes, float(length))

    def triplets(self, route: str) -> list[Triplet]:
        """The route's triplets in order: ids and actions only."""
        with self._lock:
            rows = self._connection().execute(
                "SELECT idx, image_before, action_kind, action_value, image_after FROM triplets "
                "WHERE route_id = ? ORDER BY idx", (self._route_id(route),)).fetchall()
        return [Triplet(i, b, Action(kind, value), a) for i, b, kind, value, a in rows]

    def reversed_triplets(self, route: str) -> list[Triplet]:
        return reverse_triplets(self.triplets(route))

    def load_route(self, route: str, matcher: str | None = None, reverse: bool = False) -> LoadedRoute:
        """Triplets and the descriptors of `matcher` (default: the route's first) for every place;
        images stay compressed in the database until `image` is asked for one."""
        summary = self.route(route)
        matcher = matcher or summary.matchers[0]
        if matcher not in summary.matchers:
            raise RouteStoreError(f"route {route!r} has no {matcher!r} descriptors; it has "
                                  f"{', '.join(summary.matchers)}")
        triplets = self.reversed_triplets(route) if reverse else self.triplets(route)
        ids = sorted({t.image_before for t in triplets} | {t.image_after for t in triplets})
        decode = self.matcher(matcher).from_bytes
        with self._lock:
            rows = _select_in(self._connection(), "SELECT image_id, data FROM descriptors WHERE matcher = ? "
                                                  "AND image_id IN ({})", (matcher,), ids)
        return LoadedRoute(route, matcher, triplets, {image_id: decode(data) for image_id, data in rows})

    def image(self, image_id: int) -> np.ndarray:
        """The stored image (grey uint8, at the stored size), decoded."""
        with self._lock:
            row = self._connection().execute("SELECT data FROM images WHERE id = ?", (image_id,)).fetchone()
        if row is None:
            raise RouteStoreError(f"no image {image_id}")
        return cv2.imdecode(np.frombuffer(row[0], np.uint8), cv2.IMREAD_GRAYSCALE)

    def image_record(self, image_id: int) -> StoredImage:
        """An image's metadata (pose, sizes, bytes) without its pixels."""
        with self._lock:
            row = self._connection().execute(
                "SELECT id, encoding, width, height, source_width, source_height, pose_x, pose_y, pose_heading, "
                "captured, metadata, LENGTH(data) FROM images WHERE id = ?", (image_id,)).fetchone()
        if row is None:
            raise RouteStoreError(f"no image {image_id}")
        pose = None if row[6] is None else (row[6], row[7], row[8])
        return StoredImage(row[0], row[1], row[2], row[3], row[4], row[5], pose, row[9], json.loads(row[10]), row[11])

    def storage_report(self, route: str) -> StorageReport:
        """Bytes stored for a route: images and each matcher's descriptors, per image and per metre."""
        summary = self.route(route)
        with self._lock:
            rows = self._connection().execute(
                "SELECT d.matcher, SUM(LENGTH(d.data)) FROM descriptors d JOIN images i ON i.id = d.image_id "
                "WHERE i.route_id = ? GROUP BY d.matcher", (self._route_id(route),)).fetchall()
        return StorageReport(route, summary.images, summary.image_bytes, dict(rows), summary.length_m)

    # -- reverse, links, delete ------------------------------------------------------------------
    def reverse_route(self, route: str, new_name: str) -> RouteSummary:
        """Store the way back of a finished route as a new finished route sharing its images."""
        check_safe_name(new_name)
        source = self.route(route)
        if source.state != "finished":
            raise RouteStoreError(f"route {route!r} is still recording; finish it before reversing it")
        back = self.reversed_triplets(route)
        with self._transaction() as db:
            if db.execute("SELECT 1 FROM routes WHERE name = ?", (new_name,)).fetchone():
                raise RouteStoreError(f"route {new_name!r} already exists")
            metadata = {**source.metadata, "reversed_from": route}
            now = _now()
            cursor = db.execute("INSERT INTO routes (name, created, state, matchers, metadata, finished) "
                                "VALUES (?, ?, 'finished', ?, ?, ?)",
                                (new_name, now, json.dumps(source.matchers), json.dumps(metadata), now))
            db.executemany("INSERT INTO triplets VALUES (?, ?, ?, ?, ?, ?)",
                           [(cursor.lastrowid, t.index, t.image_before, t.action.kind, t.action.value, t.image_after)
                            for t in back])
        return self.route(new_name)

    def add_link(self, route_a: str, index_a: int, route_b: str, index_b: int, similarity: float,
                 action: Action | tuple[str, float] | None = None) -> Link:
        """Connect place index_a of route_a with place index_b of route_b (both finished)."""
        if action is not None and not isinstance(action, Action):
            action = Action(*action)
        with self._transaction() as db:
            ids = [self._linkable_place(db, r, i) for r, i in ((route_a, index_a), (route_b, index_b))]
            try:
                cursor = db.execute(
                    "INSERT INTO links (route_a, index_a, route_b, index_b, similarity, action_kind, action_value, "
                    "created) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (ids[0], index_a, ids[1], index_b, float(similarity), action and action.kind,
                     action and float(action.value), _now()))
            except sqlite3.IntegrityError:
                raise RouteStoreError(f"link {route_a}:{index_a} <-> {route_b}:{index_b} already exists") from None
            link_id = cursor.lastrowid
        return next(link for link in self.links() if link.id == link_id)

    def links(self, route: str | None = None) -> list[Link]:
        """All links, or those with `route` at either end."""
        query = ("SELECT l.id, a.name, l.index_a, b.name, l.index_b, l.similarity, l.action_kind, l.action_value, "
                 "l.created FROM links l JOIN routes a ON a.id = l.route_a JOIN routes b ON b.id = l.route_b")
        with self._lock:
            if route is None:
                rows = self._connection().execute(query + " ORDER BY l.id").fetchall()
            else:
                route_id = self._route_id(route)
                rows = self._connection().execute(query + " WHERE l.route_a = ? OR l.route_b = ? ORDER BY l.id",
                                                  (route_id, route_id)).fetchall()
        return [Link(r[0], r[1], r[2], r[3], r[4], r[5], None if r[6] is None else Action(r[6], r[7]), r[8])
                for r in rows]

    def delete_route(self, route: str) -> None:
        """Delete a route, its triplets and links, and its images unless another route uses them."""
        with self._transaction() as db:
            route_id = self._route_id(route)
            db.execute("DELETE FROM triplets WHERE route_id = ?", (route_id,))
            db.execute("DELETE FROM links WHERE route_a = ? OR route_b = ?", (route_id, route_id))
            _hand_over_shared_images(db, route_id)
            _delete_unused_images(db, route_id)
            db.execute("DELETE FROM routes WHERE id = ?", (route_id,))

    # -- internals -----------------------------------------------------------------------------
    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise RouteStoreError(f"the route store {self.path} is closed")
        return self._conn

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction under the store's lock; rolled back if anything raises."""
        with self._lock:
            db = self._connection()
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    def _route_id(self, name: str) -> int:
        check_safe_name(name)
        row = self._connection().execute("SELECT id FROM routes WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise RouteStoreError(f"no route {name!r}")
        return row[0]

    def _recording_route(self, name: str) -> tuple[int, tuple[str, ...]]:
        route_id = self._route_id(name)
        state, matchers = self._connection().execute("SELECT state, matchers FROM routes WHERE id = ?",
                                                     (route_id,)).fetchone()
        if state != "recording":
            raise RouteStoreError(f"route {name!r} is {state}; only a recording route takes new images")
        return route_id, tuple(json.loads(matchers))

    def _image_id(self, db: sqlite3.Connection, route: str, route_id: int, image) -> int:
        """The id of an image end of a triplet: a prepared image (inserted now), an id of this
        route's images, or None for the previous triplet's image after."""
        if isinstance(image, _PreparedImage):
            return self._insert_image(db, route_id, image)
        if image is None:
            row = db.execute("SELECT image_after FROM triplets WHERE route_id = ? ORDER BY idx DESC LIMIT 1",
                             (route_id,)).fetchone()
            if row is None:
                raise RouteStoreError(f"route {route!r} has no triplet yet: give the first image before")
            return row[0]
        owner = db.execute("SELECT route_id FROM images WHERE id = ?", (int(image),)).fetchone()
        if owner is None or owner[0] != route_id:
            raise RouteStoreError(f"image {image} is not an image of route {route!r}")
        return int(image)

    def _prepare_image(self, image: np.ndarray, matchers: Sequence[str], pose=None, metadata=None) -> _PreparedImage:
        """Everything slow about storing an image (describing, encoding), done before writing."""
        grey = grey_image(image)
        if pose is not None:
            pose = tuple(float(v) for v in pose)
            if len(pose) != 3 or not np.all(np.isfinite(pose)):
                raise ValueError(f"pose must be finite (x, y, heading), got {pose}")
        descriptors = {m: self.matcher(m).to_bytes(self.matcher(m).describe(grey)) for m in matchers}
        encoded, stored_shape = self._encode(grey)
        return _PreparedImage(grey.shape, stored_shape, encoded, pose, dict(metadata or {}), descriptors)

    def _encode(self, grey: np.ndarray) -> tuple[bytes, tuple[int, int]]:
        c = self.config
        if c.image_downscale > 1:
            size = (max(1, grey.shape[1] // c.image_downscale), max(1, grey.shape[0] // c.image_downscale))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        if c.image_format == "webp":
            ok, data = cv2.imencode(".webp", grey, [cv2.IMWRITE_WEBP_QUALITY, c.webp_quality])
        else:
            ok, data = cv2.imencode(".png", grey, [cv2.IMWRITE_PNG_COMPRESSION, c.png_compression])
        if not ok:
            raise RuntimeError(f"OpenCV could not encode a {grey.shape} image as {c.image_format}")
        return data.tobytes(), grey.shape

    def _insert_image(self, db: sqlite3.Connection, route_id: int, image: _PreparedImage) -> int:
        x, y, heading = image.pose or (None, None, None)
        cursor = db.execute(
            "INSERT INTO images (route_id, encoding, width, height, source_width, source_height, data, pose_x, "
            "pose_y, pose_heading, captured, metadata) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (route_id, self.config.image_format, image.stored_shape[1], image.stored_shape[0],
             image.source_shape[1], image.source_shape[0], image.encoded, x, y, heading, _now(),
             json.dumps(image.metadata)))
        db.executemany("INSERT INTO descriptors (image_id, matcher, data) VALUES (?, ?, ?)",
                       [(cursor.lastrowid, name, data) for name, data in image.descriptors.items()])
        return cursor.lastrowid

    def _linkable_place(self, db, route: str, index: int) -> int:
        summary = self.route(route)
        if summary.state != "finished":
            raise RouteStoreError(f"route {route!r} is still recording; only finished routes are linked")
        if not 0 <= index <= summary.triplets or summary.triplets == 0:
            raise RouteStoreError(f"place {index} is not on route {route!r} (places 0..{summary.triplets})")
        return self._route_id(route)


@dataclass(frozen=True)
class _PreparedImage:
    source_shape: tuple[int, int]
    stored_shape: tuple[int, int]
    encoded: bytes
    pose: tuple[float, float, float] | None
    metadata: dict
    descriptors: dict[str, bytes]


# ---------------------------------------------------------------------------- schema

def migrate(db: sqlite3.Connection, target: int = SCHEMA_VERSION) -> int:
    """Bring the database to schema version `target` by applying the missing migrations in order."""
    current = _schema_version(db)
    if current > SCHEMA_VERSION:
        raise RouteStoreError(f"route database schema version {current} is newer than this software's "
                              f"{SCHEMA_VERSION}; update RVS")
    for version, _, statements in MIGRATIONS:
        if current < version <= target:
            db.execute("BEGIN IMMEDIATE")
            try:
                for statement in statements:
                    db.execute(statement)
                db.execute("UPDATE schema_version SET version = ?", (version,))
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            current = version
    return current


def _schema_version(db: sqlite3.Connection) -> int:
    exists = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'schema_version'").fetchone()
    return db.execute("SELECT version FROM schema_version").fetchone()[0] if exists else 0


def _renumber_triplets(db: sqlite3.Connection, route_id: int, keep: list[int]) -> None:
    """Keep only the triplets `keep`, numbered 0.. in their order."""
    rows = db.execute("SELECT idx, image_before, action_kind, action_value, image_after FROM triplets "
                      "WHERE route_id = ? ORDER BY idx", (route_id,)).fetchall()
    kept = [rows[k] for k in keep]
    db.execute("DELETE FROM triplets WHERE route_id = ?", (route_id,))
    db.executemany("INSERT INTO triplets VALUES (?, ?, ?, ?, ?, ?)",
                   [(route_id, i, r[1], r[2], r[3], r[4]) for i, r in enumerate(kept)])


_USED_IMAGES = "SELECT image_before FROM triplets UNION SELECT image_after FROM triplets"


def _delete_unused_images(db: sqlite3.Connection, route_id: int) -> None:
    """Drop the route's images that no triplet uses (their descriptors go with them)."""
    db.execute(f"DELETE FROM images WHERE route_id = ? AND id NOT IN ({_USED_IMAGES})", (route_id,))


def _hand_over_shared_images(db: sqlite3.Connection, route_id: int) -> None:
    """Images of a route being deleted that another route (its reverse) still uses become that route's."""
    db.execute("UPDATE images SET route_id = (SELECT t.route_id FROM triplets t "
               "WHERE t.image_before = images.id OR t.image_after = images.id LIMIT 1) "
               f"WHERE route_id = ? AND id IN ({_USED_IMAGES})", (route_id,))


def _select_in(db: sqlite3.Connection, query: str, params: tuple, ids: Sequence[int], chunk: int = 500) -> list:
    """Run `query` with its `IN ({})` filled with `ids`, in chunks below SQLite's parameter limit."""
    rows = []
    for start in range(0, len(ids), chunk):
        part = ids[start:start + chunk]
        rows += db.execute(query.format(",".join("?" * len(part))), (*params, *part)).fetchall()
    return rows


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")
