"""The route store: schema and migrations, recording and finishing, lazy loading, reverse, links,
safe names, deletion, threads, and that everything survives closing and reopening."""
from __future__ import annotations

import math
import sqlite3
import threading

import cv2
import numpy as np
import pytest

from rvs_server.routes import store as routes_store
from rvs_server.routes.store import (
    DATABASE_FILE,
    MIGRATIONS,
    SCHEMA_VERSION,
    Action,
    RouteStore,
    RouteStoreConfig,
    RouteStoreError,
    Triplet,
    migrate,
    reverse_triplets,
)
from toolbox.routes.match import make_matcher


def scene(seed: int, width: int = 192, height: int = 144) -> np.ndarray:
    """A textured grey image with a bright blob: features for ORB, a cluster for the contour."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.integers(0, 160, (height, width), dtype=np.uint8), (3, 3), 0)
    cv2.circle(image, (int(rng.integers(40, width - 40)), int(rng.integers(40, height - 40))), 25, 230, -1)
    return image


@pytest.fixture
def store(tmp_path):
    with RouteStore(tmp_path / "routes") as opened:
        yield opened


def record(store: RouteStore, name: str, legs: int = 3, seed: int = 0) -> list[Triplet]:
    """A finished route: forward 1 m, turn 0.3 rad, forward 1 m, ... with poses."""
    store.create_route(name, metadata={"site": "pit"})
    first = store.add_image(name, scene(seed), pose=(0.0, 0.0, 0.0))
    triplets = []
    for i in range(legs):
        action = Action("forward", 1.0) if i % 2 == 0 else Action("turn", 0.3)
        after = store.add_image(name, scene(seed + i + 1), pose=(float(i), 0.0, 0.0))
        triplets.append(store.add_triplet(name, first if i == 0 else None, action, after))
    store.finish_route(name)
    return triplets


# ---------------------------------------------------------------------------- schema

def test_a_new_store_has_the_current_schema(store):
    assert store.schema_version == SCHEMA_VERSION == MIGRATIONS[-1][0]
    db = sqlite3.connect(store.path)
    tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"schema_version", "routes", "images", "descriptors", "triplets", "links"} <= tables
    assert db.execute("SELECT version FROM schema_version").fetchall() == [(SCHEMA_VERSION,)]
    assert [v for v, _, _ in MIGRATIONS] == list(range(1, SCHEMA_VERSION + 1))    # in order, no gaps
    db.close()


def test_an_old_version_database_is_migrated_on_open(tmp_path):
    """A version-1 database (before links) written by the old code opens, migrates, keeps its route."""
    directory = tmp_path / "old"
    directory.mkdir()
    db = sqlite3.connect(directory / DATABASE_FILE, isolation_level=None)
    assert migrate(db, target=1) == 1
    encoded = cv2.imencode(".png", scene(1))[1].tobytes()
    descriptor = make_matcher("contour").to_bytes(make_matcher("contour").describe(scene(1)))
    db.execute("INSERT INTO routes VALUES (1, 'old-route', '2024-01-01T00:00:00Z', 'finished', '[\"contour\"]', '{}')")
    for image_id in (1, 2):
        db.execute("INSERT INTO images (id, route_id, encoding, width, height, source_width, source_height, data, "
                   "captured) VALUES (?, 1, 'png', 192, 144, 192, 144, ?, '2024-01-01T00:00:00Z')",
                   (image_id, encoded))
        db.execute("INSERT INTO descriptors VALUES (?, 'contour', ?)", (image_id, descriptor))
    db.execute("INSERT INTO triplets VALUES (1, 0, 1, 'forward', 2.5, 2)")
    db.close()

    with RouteStore(directory) as store:
        assert store.schema_version == SCHEMA_VERSION
        summary = store.route("old-route")
        assert summary.state == "finished" and summary.finished is None and summary.length_m == 2.5
        loaded = store.load_route("old-route")
        assert loaded.matcher == "contour" and set(loaded.descriptors) == {1, 2}
        assert np.array_equal(store.image(1), scene(1))
        record(store, "new-route")
        link = store.add_link("old-route", 1, "new-route", 0, 0.8)               # the v2 table works
        assert link.route_a == "old-route"


def test_a_database_from_newer_software_is_refused(tmp_path):
    with RouteStore(tmp_path) as store:
        path = store.path
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    db.close()
    with pytest.raises(RouteStoreError, match="newer"):
        RouteStore(tmp_path)


def test_a_failed_migration_leaves_the_database_at_its_old_version(tmp_path, monkeypatch):
    db = sqlite3.connect(tmp_path / DATABASE_FILE, isolation_level=None)
    migrate(db, target=1)
    db.close()
    broken = (*MIGRATIONS[:1], (2, "broken", (MIGRATIONS[1][2][0], "CREATE TABLE routes (x)")))
    monkeypatch.setattr(routes_store, "MIGRATIONS", broken)
    with pytest.raises(sqlite3.OperationalError):
        RouteStore(tmp_path)
    db = sqlite3.connect(tmp_path / DATABASE_FILE)
    assert db.execute("SELECT version FROM schema_version").fetchone() == (1,)
    columns = [r[1] for r in db.execute("PRAGMA table_info(routes)")]
    assert "finished" not in columns                              # the ALTER TABLE was rolled back too
    db.close()


# ---------------------------------------------------------------------------- recording

def test_round_trip_survives_reopening(tmp_path):
    directory = tmp_path / "routes"
    with RouteStore(directory, RouteStoreConfig(image_format="png")) as store:
        triplets = record(store, "to-crater", legs=3)
        summary = store.route("to-crater")
    with RouteStore(directory) as store:
        assert store.triplets("to-crater") == triplets
        again = store.route("to-crater")
        assert again == summary
        assert again.state == "finished" and again.triplets == 3 and again.images == 4
        assert again.length_m == 2.0 and again.metadata == {"site": "pit"}
        assert again.matchers == ("features", "contour")
        record_ = store.image_record(triplets[1].image_after)
        assert record_.pose == (1.0, 0.0, 0.0) and (record_.width, record_.height) == (192, 144)
        assert np.array_equal(store.image(triplets[0].image_before), scene(0))      # PNG is lossless
        for name in ("features", "contour"):
            matcher = make_matcher(name)
            loaded = store.load_route("to-crater", name)
            assert loaded.place_images() == [t.image_before for t in triplets] + [triplets[-1].image_after]
            stored = loaded.descriptors[triplets[0].image_before]
            assert matcher.similarity(stored, matcher.describe(scene(0))) == pytest.approx(1.0)


def test_loading_a_route_reads_descriptors_without_decoding_images(store, monkeypatch):
    triplets = record(store, "lazy")

    def no_decoding(*args, **kwargs):
        raise AssertionError("an image was decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    loaded = store.load_route("lazy", "features")
    assert len(loaded.triplets) == 3 and len(loaded.descriptors) == 4
    monkeypatch.undo()
    assert store.image(triplets[0].image_before).shape == (144, 192)


def test_webp_and_downscale_are_configurable(tmp_path):
    config = RouteStoreConfig(image_format="webp", webp_quality=80, image_downscale=2)
    with RouteStore(tmp_path, config) as store:
        store.create_route("small")
        image_id = store.add_image("small", scene(3))
        record_ = store.image_record(image_id)
        assert (record_.encoding, record_.width, record_.height) == ("webp", 96, 72)
        assert (record_.source_width, record_.source_height) == (192, 144)
        decoded = store.image(image_id).astype(float)
        reference = cv2.resize(scene(3), (96, 72), interpolation=cv2.INTER_AREA).astype(float)
        assert np.abs(decoded - reference).mean() < 12
        assert record_.nbytes < scene(3).nbytes / 4


def test_colour_images_are_stored_grey(store):
    store.create_route("colour")
    colour = np.dstack([scene(4)] * 3)
    image_id = store.add_image("colour", colour)
    assert store.image(image_id).ndim == 2


def test_finishing_keeps_the_chosen_triplets_and_drops_unused_images(store):
    """Short-term memory: a detour recorded while searching is dropped when the route is finished."""
    store.create_route("search")
    a = store.add_image("search", scene(10))
    store.add_triplet("search", a, ("forward", 1.0), scene(11))
    store.add_triplet("search", None, ("turn", 0.5), scene(12))              # detour
    store.add_triplet("search", None, ("turn", -0.5), scene(13))             # back
    store.add_triplet("search", None, ("forward", 2.0), scene(14))
    before = store.route("search")
    assert before.state == "recording" and before.images == 5
    finished = store.finish_route("search", keep=[0, 3])
    assert finished.state == "finished" and finished.finished is not None
    kept = store.triplets("search")
    assert [t.index for t in kept] == [0, 1] and [t.action for t in kept] == [Action("forward", 1.0),
                                                                              Action("forward", 2.0)]
    assert finished.images == 4 and finished.length_m == 3.0       # the image only the detour used is gone
    with pytest.raises(RouteStoreError, match="finished"):
        store.add_image("search", scene(15))
    with pytest.raises(RouteStoreError, match="finished"):
        store.finish_route("search")


def test_bad_recording_requests_change_nothing(store):
    store.create_route("r")
    with pytest.raises(RouteStoreError, match="already exists"):
        store.create_route("r")
    with pytest.raises(RouteStoreError, match="no triplet yet"):
        store.add_triplet("r", None, ("forward", 1.0), scene(1))
    with pytest.raises(ValueError, match="forward distance"):
        store.add_triplet("r", scene(1), ("forward", -1.0), scene(2))
    with pytest.raises(ValueError, match="action kind"):
        Action("jump", 1.0)
    with pytest.raises(ValueError, match="unknown matcher"):
        store.create_route("s", matchers=["sift"])
    with pytest.raises(RouteStoreError, match="no route"):
        store.add_image("nowhere", scene(1))
    other = RouteStore(store.directory)
    other.create_route("other")
    foreign = other.add_image("other", scene(2))
    other.close()
    with pytest.raises(RouteStoreError, match="not an image of route"):
        store.add_triplet("r", foreign, ("forward", 1.0), scene(3))
    with pytest.raises(RouteStoreError, match="keep"):
        store.finish_route("r", keep=[0])
    summary = store.route("r")
    assert summary.triplets == 0 and summary.images == 0 and "s" not in [r.name for r in store.list_routes()]


@pytest.mark.parametrize("name", ["../etc", ".hidden", "a b", "", "x" * 129, "route/1", "naïve"])
def test_unsafe_names_are_refused_naming_the_value(store, name):
    with pytest.raises(ValueError, match="safe name") as error:
        store.create_route(name)
    assert repr(name) in str(error.value)
    assert store.list_routes() == []


# ---------------------------------------------------------------------------- listing, reverse, links, delete

def test_list_routes_reports_lengths_counts_and_bytes(store):
    record(store, "b-route", legs=2)
    record(store, "a-route", legs=4, seed=20)
    routes = store.list_routes()
    assert [r.name for r in routes] == ["a-route", "b-route"]
    a = routes[0]
    assert (a.triplets, a.images, a.length_m) == (4, 5, 2.0)
    assert a.image_bytes > 0 and a.descriptor_bytes > 0
    report = store.storage_report("a-route")
    assert report.images == 5 and set(report.descriptor_bytes) == {"features", "contour"}
    assert report.bytes_per_image == pytest.approx((a.image_bytes + a.descriptor_bytes) / 5)
    assert report.bytes_per_metre == pytest.approx(report.bytes_total / 2.0)


def test_reversed_route_goes_back_with_reversed_actions():
    forward = [Triplet(0, 1, Action("forward", 2.0), 2), Triplet(1, 2, Action("turn", 0.5), 3),
               Triplet(2, 3, Action("backward", 1.0), 4)]
    back = reverse_triplets(forward)
    assert back == [Triplet(0, 4, Action("forward", 1.0), 3), Triplet(1, 3, Action("turn", -0.5), 2),
                    Triplet(2, 2, Action("backward", 2.0), 1)]
    assert reverse_triplets(back) == forward


def test_reverse_route_is_stored_and_outlives_its_source(store):
    triplets = record(store, "out", legs=3)
    back = store.reverse_route("out", "out-back")
    assert back.state == "finished" and back.metadata["reversed_from"] == "out"
    assert store.triplets("out-back") == reverse_triplets(triplets)
    assert store.load_route("out", reverse=True).triplets == store.triplets("out-back")
    store.delete_route("out")
    assert [r.name for r in store.list_routes()] == ["out-back"]
    loaded = store.load_route("out-back", "features")
    assert len(loaded.descriptors) == 4
    assert store.image(loaded.triplets[0].image_before).shape == (144, 192)
    assert store.route("out-back").images == 4                    # the shared images changed hands
    with pytest.raises(RouteStoreError, match="already exists"):
        store.reverse_route("out-back", "out-back")


def test_links_connect_places_of_finished_routes(store):
    record(store, "p-q", legs=3)
    record(store, "r-s", legs=2, seed=30)
    store.create_route("busy")
    link = store.add_link("p-q", 2, "r-s", 1, 0.72, action=("turn", 0.4))
    assert (link.route_a, link.index_a, link.route_b, link.index_b) == ("p-q", 2, "r-s", 1)
    assert link.similarity == pytest.approx(0.72) and link.action == Action("turn", 0.4)
    store.add_link("r-s", 0, "p-q", 3, 0.5)
    assert len(store.links()) == 2 and len(store.links("p-q")) == 2
    with pytest.raises(RouteStoreError, match="already exists"):
        store.add_link("p-q", 2, "r-s", 1, 0.9)
    with pytest.raises(RouteStoreError, match="not on route"):
        store.add_link("p-q", 4, "r-s", 0, 0.9)                   # places 0..3 on a 3-triplet route
    with pytest.raises(RouteStoreError, match="recording"):
        store.add_link("p-q", 0, "busy", 0, 0.9)
    store.delete_route("r-s")
    assert store.links() == [] and store.links("p-q") == []


def test_delete_removes_route_images_and_descriptors(store):
    record(store, "gone")
    record(store, "kept", seed=40)
    store.delete_route("gone")
    db = sqlite3.connect(store.path)
    assert db.execute("SELECT COUNT(*) FROM images").fetchone() == (4,)
    assert db.execute("SELECT COUNT(*) FROM descriptors").fetchone() == (8,)
    assert db.execute("SELECT COUNT(*) FROM triplets").fetchone() == (3,)
    db.close()
    with pytest.raises(RouteStoreError, match="no route"):
        store.route("gone")


def test_a_closed_store_says_so(tmp_path):
    store = RouteStore(tmp_path)
    store.close()
    store.close()
    with pytest.raises(RouteStoreError, match="closed"):
        store.list_routes()


# ---------------------------------------------------------------------------- threads

def test_one_writer_and_readers_share_a_store(store):
    """A recording thread appends while other threads list and load: no errors, consistent counts."""
    store.create_route("live")
    start = store.add_image("live", scene(0))
    record(store, "done")
    errors: list[BaseException] = []
    stop = threading.Event()

    def writer():
        try:
            store.add_triplet("live", start, ("forward", 0.5), scene(100))
            for i in range(12):
                store.add_triplet("live", None, ("forward", 0.5), scene(101 + i))
        except BaseException as exc:       # reported below
            errors.append(exc)
        finally:
            stop.set()

    def reader():
        try:
            while not stop.is_set():
                summary = store.route("live")
                assert summary.images == summary.triplets + 1 or summary.triplets == 0
                assert len(store.load_route("done", "contour").descriptors) == 4
                store.list_routes()
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=writer)] + [threading.Thread(target=reader) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not errors, errors
    assert store.route("live").triplets == 13
    assert math.isclose(store.route("live").length_m, 6.5)
