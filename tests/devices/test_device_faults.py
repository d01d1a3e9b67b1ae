"""Device faults in the middle of every kind of job, injected through the emulators (`sim-fault`).

Each case breaks one emulated device while a job uses it: the PTU stops answering on its serial line
mid-move, the SR4000 gives no frame on the 5th view of a panorama, a camera delivers no frame during a
grab and during a stereo navigate cycle, the trigger box sends no pulse to the cameras during a
stereo DEM. Nothing of ours is mocked: the emulator goes silent and the drivers find out as they
would on the test bed. Each must end in `ERR 503` naming the device, keep the recovery set, leave the
server answering (`status` shows the part at fault), report the device still faulty on a `reset`
while the fault lasts, and after `sim-fault --clear`, `reset` and `continue` finish the job with the
product an uninterrupted run on a fresh server makes, array for array.

`pytest -s` prints the table of what each case gave.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from rvs_server.products.rasters import read_png, read_tiff

from conftest import REPO, ServerProcess, pairs, write_configs

# The stereo traverse looks ahead only, so each cycle takes a few views (the repository's full
# panoramas take 20 s a cycle). Both runs of a case use the same files.
NARROW_PAN = {"first_pan": "[-40.0, 40.0]", "cycle_pan": "[-40.0, 40.0]"}
# open ground 1.6 m from the start of the small world (tests/navigation/test_navigate.py open_goal)
NAV_GOAL = "0.18,1.62"


def navigation_toml() -> str:
    text = (REPO / "configs" / "navigation.toml").read_text()
    for key, value in {**NARROW_PAN, "orient": "false"}.items():   # orient's looks have tests of their own
        text, count = re.subn(rf"^{key} = (\[[^\]]*\]|{{[^}}]*}})", f"{key} = {value}", text, flags=re.M)
        assert count == 1, key
    return text


@dataclass(frozen=True)
class Case:
    device: str          # sim-fault --device
    job: str             # the command line the fault interrupts
    named: str           # what the 503 must name
    status_key: str      # status's dev.X of the broken part
    reset_key: str       # reset's dev.X of the device wrapper
    product: str | None  # product name; None: the reply's values are the result (move-ptu)
    progress: str | None = None  # arm when PROGRESS says this; None: before the job starts
    fails_at: str = ""   # what the last PROGRESS before the fault says the job was doing


CASES = [
    Case("ptu", "move-ptu --pan 120 --speed 5", "ptu on ", "dev.ptu", "dev.ptu", None, progress="pan ",
         fails_at="pan "),
    Case("tof", "dem-full-tof --pan -60:60 --output scan", "sr4000", "dev.tof", "dev.tof", "scan",
         progress="view 5/", fails_at="view 5/"),
    Case("camera-left", "grab-stereo --output pair", "camera left", "dev.camera_left", "dev.cameras", "pair",
         fails_at="triggering both"),
    Case("camera-right", f"navigate --to {NAV_GOAL} --sensor stereo --tolerance 0.5 --max-steps 3 --output nav",
         "camera right", "dev.camera_right", "dev.cameras", "nav",
         fails_at="cycle 2: mapping: step 2/10 pairs: view 2/"),
    Case("trigger", "dem-full --pan -60:60 --output sdem", "trigger", "dev.trigger", "dev.cameras", "sdem",
         fails_at="view 2/"),
]
TABLE: list[dict[str, str]] = []


# -- servers and products -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def configs(tmp_path_factory) -> Path:
    return write_configs(tmp_path_factory.mktemp("faults") / "configs", {"navigation.toml": navigation_toml()})


@pytest.fixture(scope="module")
def fresh(configs):
    """Start a server on a data directory of its own; any still running is stopped at the end."""
    started: list[ServerProcess] = []

    def start(name: str) -> ServerProcess:
        server = ServerProcess(data_dir=configs.parent / name, config_dir=configs)
        started.append(server)
        return server.start()

    yield start
    for server in started:
        server.stop()


@pytest.fixture(scope="module")
def clean(fresh):
    """Each case's job run uninterrupted on a fresh server (stopped once it is done): what the
    faulted run must equal. Shared by the module's cases."""
    results = {}
    for case in CASES:
        server = fresh(f"clean-{case.device}")
        with server.connect() as c:
            reply = c.command(case.job, timeout=600)
        server.stop()
        assert " OK " in reply, reply
        results[case.device] = (reply, server)
    return results


def product_files(folder: Path) -> dict[str, object]:
    """Every array a product holds (rasters, pictures, clouds) and its tables, by relative path.
    Manifests and other JSON carry times and job bookkeeping, so they are left out."""
    readers = {".tif": read_tiff, ".png": read_png, ".npy": np.load,
               ".ply": lambda p: np.frombuffer(p.read_bytes(), np.uint8), ".csv": lambda p: p.read_text()}
    return {str(p.relative_to(folder)): readers[p.suffix](p) for p in sorted(folder.rglob("*"))
            if p.suffix in readers}


def same_product(a: Path, b: Path) -> tuple[bool, str]:
    left, right = product_files(a), product_files(b)
    if left.keys() != right.keys():
        return False, f"files differ: {sorted(left.keys() ^ right.keys())}"
    for name, value in left.items():
        other = right[name]
        if isinstance(value, str):
            equal = value == other
        else:
            equal = value.shape == other.shape and np.array_equal(value, other, equal_nan=value.dtype.kind == "f")
        if not equal:
            return False, f"{name} differs"
    return True, f"{len(left)} files equal"


# -- the cases ----------------------------------------------------------------------------------


def run_until_fault(c, case: Case) -> tuple[str, str]:
    """Start the job, break the device before it or when its PROGRESS says so; the job's final reply
    and the last PROGRESS before it."""
    arm = f"sim-fault --device {case.device}"
    if case.progress is None:
        assert " OK " in c.command(arm + after_for(case))
    c.send(f"@job {case.job}")
    armed = case.progress is None
    last = ""
    while True:
        line = c.read_line(timeout=300)
        if line.startswith("job PROGRESS"):
            last = line
            if not armed and case.progress in line and "moving to" not in line:
                c.send(f"@arm {arm} --after 0")
                armed = True
        elif line.startswith("arm "):
            assert " OK " in line, line
        elif line.startswith("job "):
            assert armed, f"the job ended before the fault was armed: {line}"
            assert case.fails_at in last, f"the fault hit elsewhere: {last}"
            return line, last


AFTER = {}  # device -> --after, for faults armed before the job (filled from the clean run)


def after_for(case: Case) -> str:
    return f" --after {AFTER.get(case.device, 0)}"


@pytest.mark.parametrize("case", CASES, ids=[c.device for c in CASES])
def test_a_fault_mid_job_is_503_and_reset_continue_finish_the_job(case, clean, fresh):
    reference_reply, reference = clean[case.device]
    if case.device == "camera-right":   # silent from the 2nd view of the 2nd cycle
        AFTER[case.device] = views_of(reference, "nav/cycle-01") + 1
    elif case.device == "trigger":      # no pulse out of the box from the 2nd view on
        assert views_of(reference, "sdem") >= 2
        AFTER[case.device] = 1
    server = fresh(f"fault-{case.device}")
    started = time.monotonic()
    with server.connect() as c:
        reply, hit = run_until_fault(c, case)
        faulted = time.monotonic() - started
        assert reply.split()[1:4] == ["ERR", "503", "device"], reply
        assert case.named in reply and "stopped answering" in reply, reply
        assert re.search(r"recovery=\d+$", reply), reply
        status = pairs(c.command("status"))
        assert status["mode"] == "break" and status["recovery"] == "1", status
        assert status[case.status_key] == "fault", status
        still = pairs(c.command("reset", timeout=120))     # the fault lasts: reset says so
        assert still[case.reset_key] == "fault", still
        assert pairs(c.command("status"))["mode"] == "break"
        assert " OK " in c.command(f"sim-fault --clear --device {case.device}")
        mended = pairs(c.command("reset", timeout=120))
        assert mended[case.reset_key] == "ok", mended
        done = c.command("continue", timeout=600)
        assert " OK " in done, done
        after = pairs(c.command("status"))
        assert after["mode"] == "standby" and after["recovery"] == "0" and after[case.status_key] == "ok", after
    server.stop()
    if case.product is None:
        want, got = pairs(reference_reply), pairs(done)
        equal = (want["pan"], want["tilt"]) == (got["pan"], got["tilt"])
        detail = f"pan {got['pan']} tilt {got['tilt']}"
    else:
        equal, detail = same_product(reference.data_dir / "products" / case.product,
                                     server.data_dir / "products" / case.product)
    TABLE.append({"device": case.device, "job": case.job.split(" --output")[0], "reply": reply.split(";")[0][4:],
                  "hit at": hit.split(" ", 3)[3][:48], "fault after": f"{faulted:.1f} s",
                  "recovery kept": status["recovery"],
                  "reset while faulty": still[case.reset_key], "continue": done.split()[1] + " " + done.split()[2],
                  "products equal": f"{'yes' if equal else 'NO'} ({detail})"})
    assert equal, detail


def views_of(server: ServerProcess, part: str) -> int:
    import json
    return len(json.loads((server.data_dir / "products" / part / "views.json").read_text()))


def test_sim_fault_names_what_is_wrong_and_refuses_devices_that_are_not_emulated(server_factory):
    server = server_factory(configs={"devices.toml": "[ptu]\nenabled = false\n"})
    with server.connect() as c:
        assert "sim-fault" in pairs(c.command("help"))["commands"].split()
        assert "camera-left" in pairs(c.command("help sim-fault"))["opt.device"]
        refused = {
            "sim-fault": "400 bad-request sim-fault: give --device (ptu, tof, camera-left, camera-right, trigger, "
                         "worker) with --after N and --kind silent (worker: segv, abrt, kill, memory)",
            "sim-fault --device lens": "400 bad-request sim-fault: --device = 'lens'",
            "sim-fault --device tof --after -1": "--after = '-1': Input should be greater than or equal to 0",
            "sim-fault --device tof --kind loud": "--kind = 'loud': Input should be 'silent', 'segv'",
            "sim-fault --clear --after 2": "--clear takes no --after or --kind",
            "sim-fault --device ptu": "409 wrong-mode sim-fault: the ptu is off (devices.toml [ptu] enabled = false)",
        }
        for line, expected in refused.items():
            assert expected in c.command(line), line
        armed = pairs(c.command("sim-fault --device trigger --after 3"))
        assert (armed["state"], armed["after"], armed["kind"]) == ("armed", "3", "silent")
        assert pairs(c.command("sim-fault --clear"))["cleared"] == "tof camera-left camera-right trigger"


def test_zz_print_the_fault_table():
    """Runs last (by name): the table of every case above, for `pytest -s` and the report."""
    if not TABLE:
        pytest.skip("no fault case ran")
    keys = list(TABLE[0])
    widths = {k: max(len(k), *(len(row[k]) for row in TABLE)) for k in keys}
    print()
    print(" | ".join(k.ljust(widths[k]) for k in keys))
    print("-|-".join("-" * widths[k] for k in keys))
    for row in TABLE:
        print(" | ".join(row[k].ljust(widths[k]) for k in keys))
