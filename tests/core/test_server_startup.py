"""Start-up: configuration files are validated before anything starts, and bad ones stop it (exit 2)."""
from __future__ import annotations

import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest

from conftest import REPO, SERVER, write_configs


def start(tmp_path, *args: str, configs: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    config_dir = write_configs(tmp_path / "configs", configs)
    return subprocess.run([*SERVER, "--config-dir", str(config_dir), "--data-dir", str(tmp_path / "data"),
                           "--port", "0", "--zmq-port", "0", "--web-port", "0", *args],
                          cwd=REPO, capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)


INVALID_FILES = [
    ("server.toml", "port = 99999\n", ["server.toml", "field port", "99999", "0..65535"]),
    ("server.toml", "prot = 7400\n", ["server.toml", "field prot", "unknown field", "did you mean field port"]),
    ("devices.toml", '[ptu]\nbackend = "usb"\n', ["devices.toml", "field ptu.backend", "'usb'", "sim|serial"]),
    ("ptu.toml", "tolerance_deg = 0\n", ["ptu.toml", "field tolerance_deg", "0", "> 0 and <= 5"]),
    ("ptu.toml", "[move-ptu]\nspeed = 1000\n", ["ptu.toml [move-ptu]", "field speed", "1000", "<= 300"]),
    ("ptu.toml", "[move-ptu]\nsped = 10\n", ["ptu.toml [move-ptu]", "field sped", "unknown field"]),
    ("navigation.toml", 'holes = { tof = "unknown", stero = "hazard" }\n',
     ["navigation.toml", "field holes.stero", "unknown field", "did you mean field holes.stereo",
      "allowed: field holes.tof, field holes.stereo"]),
    ("server.toml", "port = [\n", ["server.toml", "not valid TOML"]),
]


@pytest.fixture(scope="module")
def invalid_file_starts(tmp_path_factory) -> list[subprocess.CompletedProcess]:
    """Every invalid-file start-up of the table, two at a time (each is an interpreter importing the
    server's modules on one core before it reads the files): the results, in the table's order."""
    def run(numbered):
        number, (name, text, _) = numbered
        return start(tmp_path_factory.mktemp(f"invalid-{number}"), configs={name: text})
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(run, enumerate(INVALID_FILES)))


@pytest.mark.parametrize("case", range(len(INVALID_FILES)), ids=[f"{n}-{t.strip()}" for n, t, _ in INVALID_FILES])
def test_an_invalid_file_stops_start_up_naming_file_field_value_and_rule(invalid_file_starts, case):
    result, words = invalid_file_starts[case], INVALID_FILES[case][2]
    assert result.returncode == 2, result.stderr
    for word in words:
        assert word in result.stderr, (word, result.stderr)


def test_listening_beyond_loopback_requires_a_token(tmp_path):
    result = start(tmp_path, "--host", "0.0.0.0")
    assert result.returncode == 2
    assert "requires --token-file" in result.stderr


def test_a_token_file_others_can_read_is_refused(tmp_path):
    token = tmp_path / "token"
    token.write_text("s3cret-token\n")
    token.chmod(0o644)
    result = start(tmp_path, "--token-file", str(token))
    assert result.returncode == 2
    assert "lets others read it" in result.stderr and "chmod 600" in result.stderr


def test_a_taken_port_is_a_clean_error(tmp_path):
    import socket
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config_dir = write_configs(tmp_path / "configs")
        result = subprocess.run([*SERVER, "--config-dir", str(config_dir), "--data-dir", str(tmp_path / "d"),
                                 "--port", str(port), "--zmq-port", "0", "--web-port", "0"],
                                cwd=REPO, capture_output=True,
                                text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2 and "cannot listen" in result.stderr
