"""`reinit` swaps the whole configuration or none of it, and the log directory stays bounded.

The server is built in-process from real files (no ports, no devices opened): what is checked is
the configuration it would run with after each reload.
"""
from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import pytest

from rvs_server.app import BoundedLogFile, Server
from rvs_server.protocol import BadRequest

REPO = Path(__file__).resolve().parents[2]

# One valid change and one invalid value per configuration file: (key, changed, invalid).
EDITS = {
    "server.toml": ("log_level", '"DEBUG"', '"LOUD"'),
    "devices.toml": ("baudrate", "19200", '"fast"'),
    "world.toml": ("seed", "2", '"one"'),
    "calibration.toml": ("source", '"file"', '"guess"'),
    "hopping.toml": ("max_speed_mps", "2.5", '"fast"'),
    "imaging.toml": ("grab_timeout_s", "12.0", '"long"'),
    "mapping.toml": ("overlap", "0.2", '"some"'),
    "navigation.toml": ("weight", "0.6", '"heavy"'),
    "ptu.toml": ("default_speed_deg_s", "25.0", "-4"),
    "routes.toml": ("image_width", "320", '"wide"'),
}


def edit(config_dir: Path, name: str, value: str) -> None:
    key = EDITS[name][0]
    path = config_dir / name
    text, count = re.subn(rf"^{key}\s*=\s*[^#\n]*", f"{key} = {value} ", path.read_text(), count=1, flags=re.M)
    assert count == 1, f"{name} has no line for {key}"
    path.write_text(text)


def configuration(server: Server) -> tuple:
    """What the server runs with, as plain values (so a swapped-in equal copy still compares)."""
    return (server.settings.model_dump(), server.devices_config.model_dump(), server.world_config.model_dump(),
            server.world_file, server.calibration_config.model_dump(),
            {name: (c.settings.model_dump() if c.settings is not None else None, c.defaults)
             for name, c in server.module_configs.items()})


@pytest.fixture
def make_server(tmp_path):
    made: list[Server] = []

    def make() -> Server:
        root = tmp_path / f"server{len(made)}" if made else tmp_path
        config_dir = root / "configs"
        shutil.copytree(REPO / "configs", config_dir)
        shutil.copytree(REPO / "workflows", root / "workflows")
        server = Server(config_dir, {"data_dir": str(root / "data")})
        made.append(server)
        return server

    yield make
    for server in made:  # the server's handlers sit on the shared "rvs" logger
        for handler in server.log_handlers:
            logging.getLogger("rvs").removeHandler(handler)
            handler.close()


def test_every_edit_is_valid_and_taken_by_a_reload(make_server):
    server = make_server()
    before = configuration(server)
    for name in EDITS:
        edit(server.config_dir, name, EDITS[name][1])
    server.reload_configuration()
    after = configuration(server)
    assert all(a != b for a, b in zip(before, after, strict=True) if a is not None)  # world_file stays None
    assert server.calibration_config.source == "file" and server.settings.log_level == "DEBUG"


@pytest.mark.parametrize("broken", sorted(EDITS))
def test_a_refused_reload_changes_nothing(make_server, broken):
    """Every other file changed validly, one file broken: the reply names it, nothing is taken."""
    server = make_server()
    before = configuration(server)
    for name in EDITS:
        edit(server.config_dir, name, EDITS[name][2] if name == broken else EDITS[name][1])
    with pytest.raises(BadRequest) as refused:
        server.reload_configuration()
    message = str(refused.value)
    assert "configuration not reloaded" in message and broken in message and EDITS[broken][0] in message
    assert configuration(server) == before
    assert server.calibration_config.source == "simulator"


def test_the_log_directory_keeps_a_bounded_number_of_files(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    for run in range(4):  # earlier runs' logs, oldest first
        (logs / f"rvs-2026010{run}-000000-1.log").write_text("x" * 100)
    logger = logging.getLogger("rvs-test-rotation")
    handler = BoundedLogFile(logs / "rvs-20260201-000000-2.log", max_bytes=2_000, kept=3)
    logger.addHandler(handler)
    try:
        assert sorted(p.name for p in logs.iterdir())[:1] == ["rvs-20260102-000000-1.log"]
        for i in range(500):
            logger.warning("line %04d of a long week", i)
    finally:
        logger.removeHandler(handler)
        handler.close()
    files = sorted(logs.iterdir())
    assert len(files) == 3 and all(p.stat().st_size <= 2_100 for p in files)
    assert {p.name for p in files} == {"rvs-20260201-000000-2.log", "rvs-20260201-000000-2.log.1",
                                       "rvs-20260201-000000-2.log.2"}
    assert "line 0499" in (logs / "rvs-20260201-000000-2.log").read_text()


def test_the_server_is_what_the_modules_are_told_it_is(make_server):
    """Every member of the Host protocol (rvs_server/host.py) exists on a real Server with the kind the
    protocol gives, and module state is made once per server, on first use."""
    import inspect

    from rvs_server.host import Host

    server, other = make_server(), make_server()
    hints = Host.__annotations__
    methods = [name for name, value in vars(Host).items() if inspect.isfunction(value) and not name.startswith("_")]
    missing = [name for name in [*hints, *methods] if not hasattr(server, name)]
    assert not missing, f"Server lacks {missing}"
    assert all(callable(getattr(server, name)) for name in methods)
    assert server.settings_of("mapping") is server.module_configs["mapping"].settings
    routes = server.state_of("routes")
    assert server.state_of("routes") is routes and other.state_of("routes") is not routes
    with pytest.raises(KeyError, match="keeps no state"):
        server.state_of("system")
