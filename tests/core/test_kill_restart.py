"""Kills at random moments (issue 20): SIGKILL a server running `dem-full-tof` or `navigate` at
seeded moments spread over each command's measured duration, restart it on the same data directory,
`continue` (or give the command again when it left nothing to continue), and check that

- no file is left half-written: right after the kill every file but the temporary ones parses (JSON,
  .npy/.npz, PNG, TIFF, PLY, CSV, SQLite integrity_check), and after the restart no temporary file
  is left (the server removes them at start-up and logs it; one planted per restart proves it);
- the products equal the uninterrupted run's, file for file: arrays (GeoTIFF, PNG, .npy, PLY bytes)
  exactly, JSON and CSV parsed, their numbers to 1e-9 (the map alignment's multi-threaded sums differ
  in the last bits from one uninterrupted run to the next); not product.json (times) nor
  truth/state.json (the simulation clock and odometer restart with the server).

navigate is repeatable across a kill except inside a drive: the simulated rover's drive error comes
from a random stream that restarts with the server, so the waypoints left after a kill between two
waypoints draw other errors than they would have. Such a moment must still arrive, touch no rock and
drive on from where the rover stood (no jump in the true path); its products may differ.

Each moment is drawn as a time into the reference run and taken as "so long after its PROGRESS line
number N", so that a machine busier or idler than during the reference still kills the job at the
same stage. One more moment is chosen, not drawn: inside the drive.
"""
from __future__ import annotations

import bisect
import csv
import json
import math
import random
import sqlite3
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from rvs_server.files import is_temporary

from conftest import ServerProcess, pairs, write_configs

SEED = 20261203
MOMENTS = 6                     # per command
COMMANDS = {
    "dem": "dem-full-tof --output same",
    # An open goal 2.3 m away in the small world: a full look, one drive, a look that says it arrived.
    "navigate": "navigate --to 1.33,1.83 --output nav",
}
REPLY_KEYS = {"dem": ("cells", "cell", "known", "hazardous", "views"),
              "navigate": ("cycles", "x", "y", "heading", "remaining", "driven")}
NOT_REPEATABLE = ("product.json", "state.json")  # the manifest; truth/state.json, the truth of the moment
PLANTED = ".dem.tif.tmp-1-1"    # what a write cut short by a kill leaves


@dataclass
class Reference:
    reply: dict[str, str]
    product: Path
    seconds: float
    progress: list[float]        # when each PROGRESS line came, seconds after the command was sent
    lines: list[str]             # and what it said


@dataclass
class Moment:
    """A kill `at` seconds into the reference run: `delay` seconds after its PROGRESS line number
    `after`, so that a slower or faster machine still kills at the same stage of the job."""
    name: str
    at: float
    after: int = 0
    delay: float = 0.0
    how: str = ""                # continued | repeated | finished: what the restarted server had to do
    mid_drive: bool = False
    in_flight: int = 0           # temporary files the kill left: writes it cut short
    equal: bool = False
    problem: str = ""


@pytest.fixture(scope="module")
def config_dir(tmp_path_factory) -> Path:
    return write_configs(tmp_path_factory.mktemp("kill-configs") / "configs")


@pytest.fixture(scope="module")
def references(tmp_path_factory, config_dir) -> dict[str, Reference]:
    """Each command once, uninterrupted, on a fresh data directory; both at once, as the kills run."""
    def run(name: str) -> Reference:
        server = ServerProcess(data_dir=tmp_path_factory.mktemp(f"reference-{name}") / "data",
                               config_dir=config_dir).start()
        try:
            with server.connect() as client:
                client.command("route-list")
                client.send(f"@r {COMMANDS[name]}")
                started, progress, lines = time.monotonic(), [], []
                while not (reply := client.read_line(timeout=600)).startswith(("r OK", "r ERR")):
                    if reply.startswith("r PROGRESS"):
                        progress.append(time.monotonic() - started)
                        lines.append(reply)
                seconds = time.monotonic() - started
        finally:
            server.stop()
        assert " OK " in reply, reply
        fields = pairs(reply)
        return Reference(fields, server.data_dir / "products" / fields["product"], seconds, progress, lines)

    with ThreadPoolExecutor(2) as pool:
        return dict(zip(COMMANDS, pool.map(run, COMMANDS), strict=True))


def test_kills_at_random_moments_leave_whole_files_and_the_same_products(tmp_path, config_dir, references):
    moments = drawn_moments(references) + [inside_the_drive(references["navigate"])]
    started = time.monotonic()

    def run(numbered: tuple[int, Moment]) -> Moment:
        number, moment = numbered
        return kill_and_resume(moment, tmp_path / f"{moment.name}-{number}", config_dir, references[moment.name])

    with ThreadPoolExecutor(2) as pool:  # two servers at a time, one per core
        done = list(pool.map(run, enumerate(moments)))
    for m in done:
        print(describe(m, references[m.name]))
    print(f"{len(done)} kill moments, {sum(m.equal for m in done)} products equal to the uninterrupted run's, "
          f"{sum(m.mid_drive for m in done)} inside a drive, {sum(m.in_flight > 0 for m in done)} cut a write "
          f"short; {time.monotonic() - started:.0f} s")
    problems = [f"{m.name} at {m.at:.2f} s: {m.problem}" for m in done if m.problem]
    assert not problems, "\n".join(problems)
    assert all(m.equal or m.mid_drive for m in done) and done[-1].mid_drive


def drawn_moments(references: dict[str, Reference]) -> list[Moment]:
    """MOMENTS per command, one drawn in each equal slice of its reference run's duration."""
    rng = random.Random(SEED)
    return [moment_at(name, references[name], references[name].seconds * (k + rng.uniform(0.05, 0.95)) / MOMENTS)
            for name in COMMANDS for k in range(MOMENTS)]


def describe(m: Moment, reference: Reference) -> str:
    outcome = m.problem or ("inside a drive, arrived; " if m.mid_drive else "") + ("equal" if m.equal else "differs")
    cut = f", {m.in_flight} write(s) cut short" if m.in_flight else ""
    return (f"{m.name:8s} killed at {m.at:5.2f} s of {reference.seconds:.2f} (PROGRESS {m.after} + "
            f"{1000 * m.delay:3.0f} ms): {m.how:9s} {outcome}{cut}")


def moment_at(name: str, reference: Reference, at: float) -> Moment:
    after = bisect.bisect_right(reference.progress, at)
    return Moment(name, at, after, at - (reference.progress[after - 1] if after else 0.0))


def inside_the_drive(reference: Reference) -> Moment:
    """One moment more, chosen rather than drawn (the drive is a few % of the traverse): as the rover
    sets off for its second waypoint, so the branch for kills inside a drive is always taken."""
    driving = [k for k, line in enumerate(reference.lines) if "driving to" in line]
    assert len(driving) >= 2, "the reference drive should have two waypoints at least"
    after = driving[1] + 1
    return Moment("navigate", reference.progress[after - 1] + 0.02, after, 0.02)


def kill_and_resume(moment: Moment, root: Path, config_dir: Path, reference: Reference) -> Moment:
    root.mkdir()
    try:
        kill(moment, root / "data", config_dir)
        resume(moment, root / "data", config_dir, reference)
    except AssertionError as exc:
        moment.problem = str(exc) or repr(exc)
    return moment


def kill(moment: Moment, data: Path, config_dir: Path) -> None:
    """Start a server, give it the command, SIGKILL it at the moment; check its files, and whether the
    recovery set's checkpoint lies inside a drive."""
    server = ServerProcess(data_dir=data, config_dir=config_dir).start()
    try:
        with server.connect() as client:
            client.command("route-list")  # the route store exists, so its SQLite file is checked as well
            client.send(f"@k {COMMANDS[moment.name]}")
            seen = 0
            while seen < moment.after:
                line = client.read_line(timeout=600)
                if line.startswith(("k OK", "k ERR")):
                    break
                seen += line.startswith("k PROGRESS")
            time.sleep(moment.delay)
    finally:
        server.kill()
    moment.in_flight = len(temporaries(data))
    check_whole(data, temporaries_allowed=True)
    sets = sorted((data / "recovery").glob("*.json"))
    state = json.loads(sets[-1].read_text()).get("state") if sets else None
    traverse = (state or {}).get("traverse", {})
    moment.mid_drive = bool(traverse.get("to_drive")) and len(traverse.get("true_path", [])) > 1


def resume(moment: Moment, data: Path, config_dir: Path, reference: Reference) -> None:
    planted = data / "products" / PLANTED
    planted.write_bytes(b"II*\x00 torn")
    server = ServerProcess(data_dir=data, config_dir=config_dir).start()
    try:
        assert not planted.exists() and PLANTED in server.stderr(), "a stale temporary file survived start-up"
        assert not temporaries(data), f"temporary files after the restart: {temporaries(data)}"
        with server.connect() as client:
            reply = finish(moment, client, data)
    finally:
        server.stop()
    check_whole(data, temporaries_allowed=False)
    if reply is None:  # the job had ended: its product is all there is to compare
        product = data / "products" / reference.product.name
    else:
        assert " OK " in reply, reply
        fields = pairs(reply)
        product = data / "products" / fields["product"]
        if not moment.mid_drive:
            differ = [k for k in REPLY_KEYS[moment.name] if fields.get(k) != reference.reply[k]]
            assert not differ, f"reply differs in {differ}: {reply}"
    if moment.mid_drive:
        arrived_on_from_where_it_stood(product)
        moment.equal = first_difference(reference.product, product) is None  # by chance only
        return
    assert_same_products(reference.product, product, pictures=product.name == reference.product.name)
    moment.equal = True


def finish(moment: Moment, client, data: Path) -> str | None:
    """The final reply of continuing the job, or of giving the command again when the kill came before
    the job started; None when the job had ended before the kill."""
    if int(pairs(client.command("status"))["recovery"]):
        moment.how = "continued"
        return client.command("continue", timeout=600)
    if any(json.loads(p.read_text())["status"] == "complete" for p in (data / "products").glob("*/product.json")):
        moment.how = "finished"
        return None
    moment.how = "repeated"
    return client.command(COMMANDS[moment.name], timeout=600)


# ------------------------------------------------------------------------------------ products

def assert_same_products(expected: Path, actual: Path, pictures: bool = True) -> None:
    difference = first_difference(expected, actual, pictures)
    assert difference is None, difference


def first_difference(expected: Path, actual: Path, pictures: bool = True) -> str | None:
    """File for file: the same files, arrays equal (NaN where NaN), JSON and text equal; or what differs."""
    ours, theirs = files_of(expected), files_of(actual)
    if sorted(ours) != sorted(theirs):
        return f"files differ: {sorted(set(ours) ^ set(theirs))}"
    for relative in ours:
        if relative.endswith(".png") and not pictures:
            continue  # their titles name the product
        if not same(load(expected / relative), load(actual / relative)):
            return f"{relative} differs from the uninterrupted run's"
    return None


def files_of(product: Path) -> list[str]:
    return [str(p.relative_to(product)) for p in product.rglob("*") if p.is_file() and
            (p.name != NOT_REPEATABLE[0] or p.parent != product) and
            (p.name != NOT_REPEATABLE[1] or p.parent.name != "truth")]


def same(a, b) -> bool:
    """Arrays exactly; parsed JSON and CSV with numbers to 1e-9."""
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype and \
            np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, str) and isinstance(b, str):
        return a == b or (_number(a) is not None and _number(b) is not None and same(_number(a), _number(b)))
    if isinstance(a, float) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    return a == b


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def arrived_on_from_where_it_stood(product: Path) -> None:
    traverse = json.loads((product / "traverse.json").read_text())
    truth = json.loads((product / "truth" / "traverse.json").read_text())
    path = np.array(truth["path"])[:, :2]
    goal = np.array(traverse["goal"])
    assert traverse["outcome"] == "arrived" and truth["contacts"] == 0, traverse["outcome"]
    assert np.max(np.linalg.norm(np.diff(path, axis=0), axis=1)) < 0.1, "the true path jumps"
    assert np.linalg.norm(path[-1] - goal) < 0.45


# ------------------------------------------------------------------------------------ whole files

def temporaries(data: Path) -> list[Path]:
    return [p for p in data.rglob("*") if p.is_file() and is_temporary(p.name)]


def check_whole(data: Path, temporaries_allowed: bool) -> None:
    """Every file of the data directory opens whole; temporary ones only where allowed."""
    for path in sorted(p for p in data.rglob("*") if p.is_file()):
        relative = path.relative_to(data)
        if is_temporary(path.name):
            assert temporaries_allowed, f"temporary file {relative}"
            continue
        try:
            load(path)
        except Exception as exc:  # noqa: BLE001 - any failure to read it is the finding
            raise AssertionError(f"{relative} is not whole: {type(exc).__name__}: {exc}") from None


def load(path: Path):
    """The file's content, decoded by its kind; raises if it is torn."""
    name = path.name
    if path.parent.name == "logs" and name.endswith(".log"):
        return None  # appended line by line: a kill may cut its last line, as in any log
    if name.endswith(("-wal", "-shm")):
        return None  # SQLite's journal, checked with its database
    if name == "jobs.counter":
        return int(path.read_text())
    loaders = {".json": lambda p: json.loads(p.read_text()), ".npy": lambda p: np.load(p, allow_pickle=False),
               ".npz": load_npz, ".png": load_png, ".tif": tifffile.imread, ".ply": load_ply,
               ".csv": load_csv, ".sqlite": load_sqlite}
    if path.suffix not in loaders:
        raise AssertionError(f"no check for a file like {name}: add one")
    return loaders[path.suffix](path)


def load_npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as data:
        return {key: data[key] for key in data.files}


def load_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("does not decode")
    return image


def load_ply(path: Path) -> bytes:
    """The bytes, once the header's vertex count and properties account for every one of them."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    sizes = {"float": 4, "double": 8, "uchar": 1, "ushort": 2, "int": 4}
    stride = sum(sizes[line.split()[1]] for line in header if line.startswith("property"))
    if len(raw) - end != count * stride:
        raise ValueError(f"{len(raw) - end} bytes of vertices, the header says {count} x {stride}")
    return raw


def load_csv(path: Path) -> list[list[str]]:
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    if not rows or any(len(row) != len(rows[0]) for row in rows):
        raise ValueError("rows of different lengths")
    return rows


def load_sqlite(path: Path) -> str:
    with sqlite3.connect(path) as db:
        result = db.execute("PRAGMA integrity_check").fetchone()[0]
    if result != "ok":
        raise ValueError(f"integrity_check: {result}")
    return result
