"""configs/server.toml as a model: the server's own settings and its [storage] table. Its own small
module, so the host's interface (host.py) can name the type of `server.settings` without importing the
application (app.py) or the retention rule (products/retention.py)."""
from __future__ import annotations

from pydantic import Field

from .config import Settings


class StorageSettings(Settings):
    """server.toml `[storage]`: the retention rule and the storage cap. 0 turns a limit off."""

    max_gib: float = Field(0.0, ge=0, description="keep at most this many GiB of products (oldest go first)")
    max_days: float = Field(0.0, ge=0, description="remove products older than this many days")
    cap_gib: float = Field(0.0, ge=0, description="a write that would take the products past this many GiB "
                                                  "fails as on a full disk (ERR 507); 0: only the disk limits")


class ServerConfig(Settings):
    """configs/server.toml; the command-line options override it."""

    host: str = "127.0.0.1"
    port: int = Field(7400, ge=0, le=65535)
    zmq_port: int = Field(7401, ge=0, le=65534, description="ROUTER; the PUB socket is on zmq_port + 1")
    web_port: int = Field(7403, ge=0, le=65535, description="the web view (HTTP, rvs_server/web); 0 turns it off")
    data_dir: str = "./data"
    shared_dir: str = Field("", description="where logbook copies the log; default DATA_DIR/shared")
    token_file: str | None = None
    sim_speed: float = Field(1.0, gt=0, le=10000, description="simulated seconds per wall second")
    break_timeout_s: float = Field(30.0, gt=0, description="how long break waits for a safe point")
    quit_timeout_s: float = Field(30.0, gt=0, description="how long quit waits for the job to stop")
    log_level: str = Field("INFO", pattern="^(DEBUG|INFO|WARNING|ERROR)$")
    log_file_max_mb: float = Field(10.0, gt=0, le=10_000, description="a log file rotates at this size")
    log_files_kept: int = Field(5, ge=2, le=1000, description="log files kept in DATA_DIR/logs, all runs together")
    storage: StorageSettings = Field(default_factory=StorageSettings,
                                     description="[storage]: the retention rule and the storage cap")
    native_worker: bool = Field(True, description="run the heavy native steps of jobs (COLMAP, ICP, gridding) in a "
                                "supervised child process; false: in the job's thread, where a crash there ends the "
                                "server (the behaviour before the worker, kept for comparison)")
    worker_memory_mb: int = Field(6144, ge=0, description="address space the native worker may take (MiB; it "
                                  "imports ~1.6 GB of libraries); past it the step ends, the worker is restarted; "
                                  "0: no limit")
