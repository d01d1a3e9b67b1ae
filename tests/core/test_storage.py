"""The disk over a season (issue 46, item 2): the retention rule, `products`, and a full disk.

Real server processes. The full disk is tried twice: on a real 8 MiB tmpfs the test mounts (skipped,
saying why, where mounting is not allowed) and under server.toml's storage cap, which fails writes
through the same ENOSPC path, so it runs everywhere.
"""
from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest

from rvs_server.files import is_temporary
from rvs_server.products.retention import GIB, ProductInfo, StorageSettings, choose

from conftest import ServerProcess, pairs, write_configs

DAY = 86400.0


def server_toml(storage: str) -> str:
    """The repository's server.toml with its storage.* keys replaced by `storage` (lines KEY = VALUE)."""
    text = (Path(__file__).resolve().parents[2] / "configs" / "server.toml").read_text()
    kept = [line for line in text.splitlines() if not line.startswith("storage.")]
    return "\n".join(kept + [f"storage.{line}" for line in storage.splitlines()]) + "\n"


def fake_product(root: Path, name: str, command: str, size: int, age_days: float,
                 manifest: dict | None = None) -> Path:
    """A product folder as a job leaves it, `age_days` old."""
    folder = root / name
    (folder / "truth").mkdir(parents=True)
    (folder / "data.bin").write_bytes(os.urandom(size))
    (folder / "truth" / "state.json").write_text("{}")
    (folder / "product.json").write_text(json.dumps({"name": name, "command": command, "status": "complete",
                                                     **(manifest or {})}))
    when = time.time() - age_days * DAY
    for path in [*folder.rglob("*"), folder]:
        os.utime(path, (when, when))
    return folder


def listing(reply: str) -> dict[str, str]:
    return {k[2:]: v for k, v in pairs(reply).items() if k.startswith("p.")}


# ------------------------------------------------------------------------------------------------ the rule


def info(name: str, command: str, size: int, age_days: float) -> ProductInfo:
    return ProductInfo(name, Path(name), command, "complete", size, time.time() - age_days * DAY)


def test_the_rule_removes_oldest_first_down_to_the_size_and_past_the_age():
    infos = [info("a", "x", 400, 9), info("b", "x", 400, 8), info("c", "y", 400, 7), info("d", "x", 400, 1)]
    by_size = choose(StorageSettings(max_gib=1000 / GIB), infos, protected={"a": "recovery:1"})
    assert [p.name for p in by_size] == ["b", "c"]          # a is protected; 1600 - 800 <= 1000
    by_age = choose(StorageSettings(max_days=7.5), infos, protected={})
    assert [p.name for p in by_age] == ["a", "b"]
    assert choose(StorageSettings(), infos, protected={}) == []   # no limits: nothing goes


def test_retention_keeps_what_is_referred_to_and_the_dry_run_changes_nothing(tmp_path):
    configs = write_configs(tmp_path / "configs", {"server.toml": server_toml("max_days = 1.0\nmax_gib = 0")})
    data = tmp_path / "data"
    products = data / "products"
    products.mkdir(parents=True)
    server = ServerProcess(data_dir=data, config_dir=configs).start()
    try:
        # Made while the server runs, so start-up's pass has not seen them.
        for i in (1, 2, 3):
            fake_product(products, f"old-grab-{i}", "grab-tof", 20_000, 10 + 3 - i)     # old-grab-3 is newest
        fake_product(products, "old-recovered", "dem-full-tof", 20_000, 12)
        fake_product(products, "dem-full-tof-new", "dem-full-tof", 20_000, 0.1)
        fake_product(products, "route-r1", "route-record", 20_000, 11)
        fake_product(products, "route-r2", "route-record", 20_000, 0.2)
        fake_product(products, "hop-001", "hop", 20_000, 13)
        fake_product(products, "hop-002", "hop", 20_000, 0.1)
        fake_product(products, "hop-plan-001", "hop-plan", 20_000, 13)
        fake_product(products, "hop-plan-002", "hop-plan", 20_000, 0.1)
        fake_product(products, "hop-map-001", "hop-map", 20_000, 12,
                     {"inputs": [{"hop": "hop-001", "plan": "hop-plan-001"}]})
        (data / "recovery" / "77.json").write_text(json.dumps({
            "job": "77", "command": "dem-full-tof", "options": {}, "line": "dem-full-tof",
            "state": {"product": "old-recovered"}, "reason": "break", "devices": []}))
        (data / "routes").mkdir(exist_ok=True)
        with sqlite3.connect(data / "routes" / "routes.sqlite") as db:
            db.execute("CREATE TABLE routes (id INTEGER PRIMARY KEY, name TEXT)")
            db.execute("INSERT INTO routes (name) VALUES ('r1')")
        before = sorted(p.name for p in products.iterdir())

        with server.connect() as client:
            shown = client.command("products")
            assert " OK " in shown, shown
            fields, rows = pairs(shown), listing(shown)
            assert int(fields["count"]) == len(before) and sorted(rows) == before
            assert int(fields["bytes"]) >= 20_000 * len(before)
            size, command, status = rows["old-grab-1"].split()[:3]
            assert int(size) > 20_000 and (command, status) == ("grab-tof", "complete")
            assert "keep=recovery:77" in rows["old-recovered"] and "keep=route:r1" in rows["route-r1"]
            assert "keep=hop-map" in rows["hop-001"] and "keep=newest:grab-tof" in rows["old-grab-3"]

            dry = client.command("products --prune --dry-run")
            assert " OK " in dry, dry
            assert pairs(dry)["would_remove"] == "2"
            assert sorted(pairs(dry)["would_remove.names"].split()) == ["old-grab-1", "old-grab-2"]
            assert sorted(p.name for p in products.iterdir()) == before       # nothing changed

            pruned = client.command("products --prune")
            assert " OK " in pruned and pairs(pruned)["removed"] == "2", pruned
            after = sorted(p.name for p in products.iterdir())
            assert after == sorted(set(before) - {"old-grab-1", "old-grab-2"})
            assert not [p for p in products.iterdir() if p.name.startswith(".")]
            assert " OK " in client.command("status")
            assert "--dry-run goes with --prune" in client.command("products --dry-run")
        log = server.data_dir / "logs"
        assert any("removed 2 product(s)" in p.read_text() for p in log.glob("rvs-*.log"))
    finally:
        server.stop()

    # At start-up the rule runs again: the recovery set dropped, its product goes too (it is old).
    (data / "recovery" / "77.json").unlink()
    server = ServerProcess(data_dir=data, config_dir=configs).start()
    try:
        names = {p.name for p in products.iterdir()}
        assert "old-recovered" not in names and "dem-full-tof-new" in names and "route-r1" in names
        assert any("retention (start-up): removed 1 product(s)" in p.read_text()
                   for p in (data / "logs").glob("rvs-*.log"))
    finally:
        server.stop()


# ------------------------------------------------------------------------------------------------ a full disk


def check_full_then_continue(server: ServerProcess, free_space) -> None:
    """grab-tof on a full disk: 507 naming the path and the free space, status answers, the folder holds
    only whole files, and after free_space() `continue` finishes the same product."""
    products = server.data_dir / "products"
    with server.connect() as client:
        reply = client.command("grab-tof --output full", timeout=120)
        assert reply.split()[1:4] == ["ERR", "507", "storage"], reply
        assert "no space left writing " + str(products / "full") in reply and " free " in reply, reply
        assert "recovery=" in reply and "continue" in reply, reply
        status = pairs(client.command("status"))
        assert status["mode"] == "break" and status["recovery"] == "1", status
        folder = products / "full"
        names = [p for p in folder.rglob("*") if p.is_file()]
        assert not [p for p in names if is_temporary(p.name)], names
        manifest = json.loads((folder / "product.json").read_text())
        assert manifest["status"] == "interrupted"
        for relative in manifest["files"]:       # what it lists and holds is whole
            path = folder / relative
            if path.exists():
                assert path.stat().st_size > 0
        assert not (folder / "distance.png").exists() or "distance.png" in manifest["files"]

        free_space()
        done = client.command("continue", timeout=120)
        assert " OK " in done and pairs(done)["product"] == "full", done
        manifest = json.loads((folder / "product.json").read_text())
        assert manifest["status"] == "complete" and (folder / "distance.png").stat().st_size > 100_000
        assert pairs(client.command("status"))["mode"] == "standby"


def test_a_storage_cap_makes_the_job_end_507_and_continue_finishes_it(tmp_path):
    configs = write_configs(tmp_path / "configs",
                            {"server.toml": server_toml(f"max_gib = 0\nmax_days = 0\ncap_gib = {430_000 / GIB:.9f}")})
    data = tmp_path / "data"
    filler = fake_product(data / "products", "filler", "grab-tof", 200_000, 0)
    server = ServerProcess(data_dir=data, config_dir=configs).start()
    try:
        check_full_then_continue(server, lambda: shutil.rmtree(filler))
    finally:
        server.stop()


@pytest.fixture
def small_disk(tmp_path):
    """An 8 MiB tmpfs mounted at tmp_path/data for the test, or a skip saying why it cannot be."""
    data = tmp_path / "data"
    data.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (euid 0); the storage-cap test covers the same path")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(data)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.skip(f"this machine forbids mounting a tmpfs ({done.stderr.strip() or done.returncode}); "
                    f"the storage-cap test covers the same path")
    try:
        yield data
    finally:
        if subprocess.run(["umount", str(data)]).returncode != 0:
            subprocess.run(["umount", "-l", str(data)])


def test_a_full_disk_makes_the_job_end_507_and_continue_finishes_it(tmp_path, small_disk):
    configs = write_configs(tmp_path / "configs", {"server.toml": server_toml("max_gib = 0\nmax_days = 0")})
    server = ServerProcess(data_dir=small_disk, config_dir=configs).start()
    try:
        filler = small_disk / "filler.bin"
        free = shutil.disk_usage(small_disk).free
        # Room for the recovery set, the log lines and the small files, not for the 250 KiB picture.
        filler.write_bytes(b"\0" * (free - 160 * 1024))
        check_full_then_continue(server, filler.unlink)
    finally:
        server.stop()
