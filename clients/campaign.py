"""`rvs campaign`: many missions, each on its own real server, run on Dask distributed (issue 28).

    rvs campaign FILE [--workers N | --scheduler ADDRESS] [--out DIR]

A campaign file (TOML) names the runs:

    name = "ptu-look"
    mission = "ptu-look.rvs"      # relative to the campaign file; ${VAR}s as in `rvs mission`
    sim_speed = 20.0              # simulated seconds per wall second of every server (default 1)
    timeout_s = 600               # seconds of silence tolerated per mission line (default 600)

    [world]                       # world.toml options of every run, over configs/world.toml
    size_m = [12.0, 12.0]

    [[run]]                       # a table of runs: `seed` (--world-seed) or `world_file` (--world,
    seed = 3                      # relative to the campaign file) picks the world, every other key
    PAN = 20                      # is a ${VAR} of the mission

    [product]                     # and/or: one run per combination of these lists
    seed = [1, 2]
    PAN = [20, 40]

    [collect]                     # the columns of the summary, from each run:
    pan = "move.pan"              #   field `pan` of the final reply of the line tagged @move (or of
                                  #   the last line of that command name: "grab-tof.product")
    rows = "dem:product.json:grid.rows"   # a JSON path in a file of the product that line wrote

A measurement campaign adds Python where a table is not enough (tests/bench/campaigns/navigation.toml):

    runs_from = "../navigation_scoring.py:runs"     # FUNCTION(**runs_args) -> the runs (dicts), appended
    [runs_args]                                     #   to [[run]] and [product]; a run may hold `world`
    scenes = 10                                     #   (world.toml options over [world]) and `configs`
                                                    #   ({"navigation.toml": {...}})
    score = "../navigation_scoring.py:score"        # FUNCTION(run, data_dir) -> more columns, computed
                                                    #   in the worker after the mission (a `pid`
                                                    #   parameter, if it has one, gets the server's)
    report = "../navigation_scoring.py:report"      # FUNCTION(records) -> the text of DIR/report.md

A run that is not one fixed mission on one server (a hop launched where the last hop-plan chose, a
route taught on one server and repeated on fresh ones) is played by Python instead of a mission
(tests/bench/campaigns/hopping.toml):

    execute = "../hopping_scoring.py:execute"       # FUNCTION(run, run_dir, sim_speed) -> the run's values
                                                    #   (a dict, JSON-serialisable); raising fails the attempt

An `execute` campaign has no `mission`, [world], [collect] or `score`: the function starts what servers
it needs under run_dir (OUT/runs/RUN/, the attempt's marker file already in it: attempt N is the Nth
`attempt-*` file) and its prints go to run_dir/execute-N.log. Everything else is the same: runs from
[[run]], [product] and runs_from, one Dask task per run with the resource servers=1, the retry, the
results file and resuming, the progress, the summary and the report hook.

A hook is FILE.py:FUNCTION (relative to the campaign file; workers on other machines need the same
path) or MODULE:FUNCTION (importable where the campaign runs).

Each run is a real `rvs-server` process (`--port 0`, its ready line read; `--web-port 0`: no web
view) with its own configuration and data directories under OUT/runs/RUN/, driven by the mission
runner in-process through the client library and stopped with `quit`. Besides the run's own
variables the mission sees ${RUN} (the run's name) and ${ATTEMPT} (1 on its first attempt, 2 on its
retry, ... counted by marker files in the run's directory).

Why Dask distributed: the same code runs on this machine (a LocalCluster of N worker processes, the
default) and on an existing scheduler with workers on other machines (`--scheduler ADDRESS`), and it
gives retries and lost-worker rescheduling for free. Every worker has the resource `servers=1` and
every run asks for it, so one machine runs at most as many servers as it has workers started with
`--resources servers=1`, whatever the thread count. A run whose mission fails or whose collected
values are missing raises in its task; Dask runs it once more (`retries=1`, also when its worker is
lost), and a run that fails again is written to the results file with its error and reported,
never dropped.

Results are appended (fsynced) to OUT/results.jsonl with clients/run_log.RunLog as they arrive, and
OUT/summary.csv, summary.json and summary.md are rewritten after each one, so running the same
command again resumes the campaign: runs that finished are not run again, failed ones are retried.
Changing the mission, the world table, sim_speed, the collect table or the score or execute hook's
name makes a new campaign (`settings` carry a digest of them); the old lines stay in the file.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import hashlib
import importlib
import importlib.util
import inspect
import io
import itertools
import json
import os
import re
import selectors
import shutil
import socket
import subprocess
import sys
import time
import tomllib
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rvs_server.protocol import split_tag

from . import mission
from .gnc import Result, RvsClient, RvsClientError
from .run_log import RunLog, write_atomic

EXIT_OK, EXIT_FAILED, EXIT_NOT_STARTED = 0, 1, 2
REPO = Path(__file__).resolve().parent.parent
# The keys of a run that set up its server (its world, its configuration); all others are ${VARS}.
WORLD_KEYS = ("seed", "world_file", "world", "configs")
RESULTS_FILE = "results.jsonl"
READY_TIMEOUT_S = 120.0


class CampaignError(Exception):
    """A campaign file that cannot be run as written."""


class RunFailed(Exception):
    """One attempt of a run failed (the mission stopped, the server did not start, a value is missing)."""


# ---------------------------------------------------------------------------------------------
# The campaign file


@dataclass
class Campaign:
    name: str
    path: Path
    mission_name: str
    mission_text: str
    world: dict[str, Any]
    runs: list[dict[str, Any]]
    collect: dict[str, str]
    sim_speed: float = 1.0
    timeout_s: float = 600.0
    score: str = ""       # MODULE:FUNCTION(run, data_dir[, pid]) -> columns, after the mission
    report: str = ""      # MODULE:FUNCTION(records) -> the campaign's own summary text
    execute: str = ""     # MODULE:FUNCTION(run, run_dir, sim_speed) -> values, instead of server and mission

    @property
    def settings(self) -> dict[str, Any]:
        """What makes two runs of the same name comparable (RunLog's `settings`)."""
        # The score hook by its file's name and function: the same campaign checked out elsewhere resumes.
        basis = [self.mission_text, self.world, self.collect, self.sim_speed] + \
            ([self.score.rsplit("/", 1)[-1]] if self.score else []) + \
            ([{"execute": self.execute.rsplit("/", 1)[-1]}] if self.execute else [])
        digest = hashlib.sha256(json.dumps(basis, sort_keys=True).encode()).hexdigest()[:16]
        return {"campaign": self.name, "digest": digest}


def hook(spec: str, where: str) -> Callable[..., Any]:
    """The function a campaign file names as FILE.py:FUNCTION (an absolute path by now: load_campaign
    resolves it) or MODULE:FUNCTION."""
    module_name, colon, name = spec.rpartition(":")
    if not colon or not module_name or not name:
        raise CampaignError(f"{where}: {spec!r}: expected FILE.py:FUNCTION or MODULE:FUNCTION")
    try:
        function = getattr(_hook_module(module_name), name)
    except (ImportError, AttributeError, OSError) as exc:
        raise CampaignError(f"{where}: {spec!r}: {exc}") from None
    if not callable(function):
        raise CampaignError(f"{where}: {spec!r} is not a function")
    return function


def call_hook(spec: str, *args: Any, **kwargs: Any) -> Any:
    """Call the hook FILE.py:FUNCTION (or MODULE:FUNCTION) with these arguments: what a hook hands a
    process pool. A FILE.py hook's module exists only in the process that loaded it, so its functions
    do not pickle by name into a pool's fresh process; their spec does, and each process loads it."""
    return hook(spec, "call_hook")(*args, **kwargs)


def load_campaign(path: str | Path) -> Campaign:
    path = Path(path).resolve()
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise CampaignError(f"cannot read {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise CampaignError(f"{path}: {exc}") from None
    known = {"name", "mission", "sim_speed", "timeout_s", "world", "run", "product", "collect", "runs_from",
             "runs_args", "score", "report", "execute"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise CampaignError(f"{path.name}: unknown keys {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    for key in ("runs_from", "score", "report", "execute"):
        if key in data and not isinstance(data[key], str):
            raise CampaignError(f"{path.name}: {key} = {data[key]!r}: expected a string FILE.py:FUNCTION or "
                                f"MODULE:FUNCTION")
    if "execute" in data:
        clash = [key for key in ("mission", "world", "collect", "score") if key in data]
        if clash:
            raise CampaignError(f"{path.name}: execute = {data['execute']!r} plays each run itself: "
                                f"{', '.join(clash)} cannot be given with it")
        mission_name = mission_text = ""
    elif "mission" not in data:
        raise CampaignError(f"{path.name}: no `mission` file (or `execute` hook)")
    else:
        mission_path = (path.parent / data["mission"]).resolve()
        mission_name = mission_path.name
        try:
            mission_text = mission_path.read_text(encoding="utf-8")
        except OSError as exc:
            raise CampaignError(f"cannot read mission {mission_path}: {exc.strerror}") from None
    runs = [dict(run) for run in data.get("run", [])]
    product = data.get("product", {})
    if product:
        if not all(isinstance(values, list) and values for values in product.values()):
            raise CampaignError(f"{path.name}: every key of [product] must be a non-empty list")
        names = list(product)
        runs += [dict(zip(names, combination, strict=True)) for combination in itertools.product(*product.values())]
    for key in ("runs_from", "score", "report", "execute"):
        if key in data:
            data[key] = _resolved(str(data[key]), path.parent)
    if "runs_from" in data:
        made = hook(str(data["runs_from"]), f"{path.name} runs_from")(**dict(data.get("runs_args", {})))
        if not isinstance(made, list) or not all(isinstance(run, dict) for run in made):
            raise CampaignError(f"{path.name}: runs_from must give a list of runs (dicts)")
        runs += [dict(run) for run in made]
    for key in ("score", "report"):
        if key in data:
            hook(str(data[key]), f"{path.name} {key}")     # refused now, not in every worker
    if "execute" in data:
        played = hook(str(data["execute"]), f"{path.name} execute")
        try:
            inspect.signature(played).bind(run={}, run_dir=path.parent, sim_speed=1.0)
        except TypeError:
            raise CampaignError(f"{path.name} execute: {data['execute']!r} must take (run, run_dir, sim_speed)") \
                from None
        except ValueError:   # no signature to read (a builtin): it is called as it is
            pass
    if not runs:
        raise CampaignError(f"{path.name}: no runs ([[run]] tables, a [product] of lists, or runs_from)")
    keys = [RunLog.key(run) for run in runs]
    if len(set(keys)) != len(keys):
        raise CampaignError(f"{path.name}: the same run is named twice")
    collect = {str(column): str(spec) for column, spec in data.get("collect", {}).items()}
    campaign = Campaign(name=str(data.get("name", path.stem)), path=path, mission_name=mission_name,
                        mission_text=mission_text, world=dict(data.get("world", {})), runs=runs, collect=collect,
                        sim_speed=float(data.get("sim_speed", 1.0)), timeout_s=float(data.get("timeout_s", 600.0)),
                        score=str(data.get("score", "")), report=str(data.get("report", "")),
                        execute=str(data.get("execute", "")))
    problems = []
    for run in runs:   # every run's mission must parse before anything starts
        if campaign.execute:
            try:
                json.dumps(run)
            except (TypeError, ValueError) as exc:
                problems.append(f"run {run_name(run)}: not JSON ({exc})")
        else:
            try:
                mission.parse_mission(mission_text, variables_of(run, run_name(run), 1))
            except mission.MissionError as exc:
                problems += [f"run {run_name(run)}: {problem}" for problem in exc.problems]
        if "world_file" in run:
            run["world_file"] = str((path.parent / run["world_file"]).resolve())
    for column, spec in collect.items():
        try:
            parse_collect(spec)
        except ValueError as exc:
            problems.append(f"collect {column}: {exc}")
    if problems:
        raise CampaignError("; ".join(problems))
    return campaign


def run_name(run: dict[str, Any]) -> str:
    """A run's directory name: its keys and values, made a safe name."""
    text = "_".join(f"{key}-{value}" for key, value in run.items())
    safe = re.sub(r"[^A-Za-z0-9_.+-]+", "-", text).strip("-.") or "run"
    if len(safe) > 60 or safe != text:
        safe = f"{safe[:50]}-{hashlib.sha256(RunLog.key(run).encode()).hexdigest()[:8]}"
    return safe


def variables_of(run: dict[str, Any], name: str, attempt: int) -> dict[str, str]:
    variables = {key: str(value) for key, value in run.items() if key not in WORLD_KEYS}
    variables.setdefault("RUN", name)
    variables["ATTEMPT"] = str(attempt)
    return variables


def parse_collect(spec: str) -> tuple[str, str, str | None]:
    """"TAG.FIELD" -> (TAG, FIELD, None); "TAG:FILE:json.path" -> (TAG, json.path, FILE)."""
    if ":" in spec:
        parts = spec.split(":", 2)
        if len(parts) != 3 or not all(parts):
            raise ValueError(f"{spec!r}: expected TAG:FILE:json.path")
        return parts[0], parts[2], parts[1]
    tag, dot, name = spec.partition(".")
    if not dot or not tag or not name:
        raise ValueError(f"{spec!r}: expected TAG.FIELD or TAG:FILE:json.path")
    return tag, name, None


def _hook_module(name: str) -> Any:
    if not name.endswith(".py"):
        return importlib.import_module(name)
    path = Path(name)
    key = f"rvs_campaign_hook_{hashlib.sha256(str(path).encode()).hexdigest()[:12]}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[key]
        raise
    return module


def _resolved(spec: str, folder: Path) -> str:
    """A FILE.py:FUNCTION hook with its file made absolute (relative to the campaign file)."""
    module_name, colon, name = spec.rpartition(":")
    if colon and module_name.endswith(".py"):
        return f"{(folder / module_name).resolve()}:{name}"
    return spec


# ---------------------------------------------------------------------------------------------
# One run (what a Dask task does, on whichever worker gets it)


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    """A value as TOML writes it inline: a dict (in a list, or nested) as an inline table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(str(key))} = {_toml_value(item)}" for key, item in value.items()) + " }" \
            if value else "{}"
    raise CampaignError(f"cannot write {value!r} to a configuration file")


def dump_toml(data: dict[str, Any], prefix: str = "") -> str:
    """The small TOML the configuration files need: scalars, lists (of inline tables too) and nested tables."""
    lines = [f"{_toml_key(key)} = {_toml_value(value)}" for key, value in data.items() if not isinstance(value, dict)]
    for key, value in data.items():
        if isinstance(value, dict):
            name = f"{prefix}{_toml_key(key)}"
            lines += ["", f"[{name}]", dump_toml(value, f"{name}.")]
    return "\n".join(lines)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in over.items():
        merged[key] = _merge(merged[key], value) if isinstance(value, dict) and isinstance(merged.get(key), dict) \
            else value
    return merged


def override_config(config_dir: Path, name: str, over: dict[str, Any]) -> None:
    """Set `over`'s keys in the configuration file `name` of `config_dir` (nested tables merged, the rest kept)."""
    if Path(name).name != name or not name.endswith(".toml") or not (config_dir / name).is_file():
        raise RunFailed(f"configs: {name!r} is not a configuration file of configs/")
    merged = _merge(tomllib.loads((config_dir / name).read_text()), over)
    (config_dir / name).write_text(dump_toml(merged) + "\n")


class RecordingClient:
    """The mission runner's client: every final reply kept by its line's @TAG and command name."""

    def __init__(self, client: RvsClient):
        self.client = client
        self.replies: dict[str, Result] = {}

    def stream(self, line: str):
        tag, rest = split_tag(line)
        for item in self.client.stream(line):
            if isinstance(item, Result):
                words = rest.split()
                if words:
                    self.replies[words[0]] = item
                if tag:
                    self.replies[tag] = item
            yield item


def _json_path(data: Any, path: str) -> Any:
    """`a.0.b` in nested dicts and lists; a key with dots in it (`grids.dem.tif.rows`) is matched whole,
    the longest key that exists winning."""
    parts = path.split(".")
    while parts:
        if isinstance(data, list):
            data, parts = data[int(parts[0])], parts[1:]
            continue
        for end in range(len(parts), 0, -1):
            key = ".".join(parts[:end])
            if isinstance(data, dict) and key in data:
                data, parts = data[key], parts[end:]
                break
        else:
            raise KeyError(".".join(parts))
    return data


def collect_values(collect: dict[str, str], replies: dict[str, Result]) -> dict[str, Any]:
    values = {}
    for column, spec in collect.items():
        tag, name, file_name = parse_collect(spec)
        if tag not in replies:
            raise RunFailed(f"collect {column}: no line tagged @{tag} (or command {tag}) answered OK")
        reply = replies[tag]
        try:
            if file_name is None:
                values[column] = reply[name]
            else:
                product = Path(reply["path"])
                values[column] = _json_path(json.loads((product / file_name).read_text()), name)
        except (KeyError, IndexError, ValueError, OSError) as exc:
            raise RunFailed(f"collect {column} ({spec}): {exc}") from None
    return values


class Server:
    """One rvs-server process for one attempt of a run."""

    def __init__(self, run_dir: Path, world: dict[str, Any], run: dict[str, Any], sim_speed: float):
        self.run_dir = run_dir
        config_dir = run_dir / "configs"
        shutil.rmtree(config_dir, ignore_errors=True)
        shutil.copytree(REPO / "configs", config_dir)
        shutil.copytree(REPO / "workflows", run_dir / "workflows", dirs_exist_ok=True)
        base = tomllib.loads((config_dir / "world.toml").read_text())
        (config_dir / "world.toml").write_text(dump_toml(_merge(_merge(base, world), run.get("world", {}))) + "\n")
        for name, over in run.get("configs", {}).items():     # a run's own settings, over the repository's
            override_config(config_dir, name, over)
        self.data_dir = run_dir / "data"
        shutil.rmtree(self.data_dir, ignore_errors=True)   # a retry starts from nothing
        args = [sys.executable, "-m", "rvs_server", "--port", "0", "--zmq-port", "0", "--web-port", "0",
                "--data-dir", str(self.data_dir), "--config-dir", str(config_dir), "--sim-speed", str(sim_speed)]
        if "seed" in run:
            args += ["--world-seed", str(run["seed"])]
        if "world_file" in run:
            args += ["--world", str(run["world_file"])]
        self.stderr_path = run_dir / "server.stderr"
        with open(self.stderr_path, "ab") as err:
            self.proc = subprocess.Popen(args, cwd=run_dir, stdout=subprocess.PIPE, stderr=err,
                                         stdin=subprocess.DEVNULL)
        self.host, self.port = self._ready(READY_TIMEOUT_S)

    def _ready(self, timeout: float) -> tuple[str, int]:
        """Read stdout up to `rvs-server ready tcp=HOST:PORT ...`."""
        assert self.proc.stdout is not None
        selector = selectors.DefaultSelector()
        selector.register(self.proc.stdout, selectors.EVENT_READ)
        deadline, buffer = time.monotonic() + timeout, b""
        try:
            while time.monotonic() < deadline:
                if not selector.select(max(0.0, deadline - time.monotonic())):
                    break
                chunk = os.read(self.proc.stdout.fileno(), 4096)
                if not chunk:
                    raise RunFailed(f"rvs-server exited ({self.proc.wait()}): {self._tail()}")
                buffer += chunk
                for line in buffer.decode(errors="replace").splitlines():
                    if line.startswith("rvs-server ready"):
                        fields = dict(part.split("=", 1) for part in line.split()[2:] if "=" in part)
                        host, port = fields["tcp"].rsplit(":", 1)
                        return host, int(port)
        finally:
            selector.close()
        self.stop()
        raise RunFailed(f"rvs-server not ready after {timeout:g} s: {self._tail()}")

    def _tail(self) -> str:
        try:
            return " | ".join(self.stderr_path.read_text(errors="replace").strip().splitlines()[-3:])
        except OSError:
            return ""

    def stop(self, client: RvsClient | None = None) -> int | None:
        if self.proc.poll() is None:
            try:
                if client is not None and not client.closed:
                    client.send("quit", timeout=60)
            except RvsClientError:
                pass
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        if self.proc.stdout:
            self.proc.stdout.close()
        return self.proc.returncode


def next_attempt(run_dir: Path) -> int:
    """Count this attempt with a marker file (`attempt-N`) in the run's directory; N from 1."""
    run_dir.mkdir(parents=True, exist_ok=True)
    attempt = 1 + sum(1 for _ in run_dir.glob("attempt-*"))
    (run_dir / f"attempt-{attempt}").write_text(f"{socket.gethostname()} {os.getpid()} {time.time():.3f}\n")
    return attempt


def execute_run(spec: dict[str, Any]) -> dict[str, Any]:
    """One attempt of one run: start its server, play the mission, collect, quit. Raises RunFailed
    (so that Dask retries it) when anything of it failed; returns the run's result otherwise."""
    started = time.monotonic()
    if spec.get("execute"):
        return _played(spec, started)
    run, name = spec["run"], spec["name"]
    run_dir = Path(spec["run_dir"])
    attempt = next_attempt(run_dir)
    lines = mission.parse_mission(spec["mission_text"], variables_of(run, name, attempt))
    server = Server(run_dir, spec["world"], run, spec["sim_speed"])
    client = None
    transcript = open(run_dir / f"mission-{attempt}.log", "w", encoding="utf-8")
    try:
        client = RvsClient(server.host, server.port, timeout=spec["timeout_s"])
        recorder = RecordingClient(client)
        report = mission.run_mission(recorder, lines, lambda text: print(text, file=transcript, flush=True))
        outcome = mission.summary(spec["mission_name"], report)
        print(outcome, file=transcript, flush=True)
        if report.exit_status != mission.EXIT_OK:
            raise RunFailed(f"attempt {attempt}: {outcome}")
        values = collect_values(spec["collect"], recorder.replies)
        if spec.get("score"):
            scorer = hook(spec["score"], "score")
            extra = {"pid": server.proc.pid} if _takes(scorer, "pid") else {}   # while the server still runs
            values.update(scorer(run=run, data_dir=server.data_dir, **extra))
    except RvsClientError as exc:
        raise RunFailed(f"attempt {attempt}: {exc}") from None
    finally:
        transcript.close()
        server.stop(client)
        if client is not None:
            client.close()
    return {"run": run, "seconds": time.monotonic() - started, "attempt": attempt, "host": socket.gethostname(),
            "values": values}


def _played(spec: dict[str, Any], started: float) -> dict[str, Any]:
    """One attempt of a run of an `execute` campaign: the hook plays it (its prints to execute-N.log)."""
    run, run_dir = spec["run"], Path(spec["run_dir"])
    attempt = next_attempt(run_dir)
    with open(run_dir / f"execute-{attempt}.log", "w", encoding="utf-8") as transcript:
        try:
            with contextlib.redirect_stdout(transcript):
                values = hook(spec["execute"], "execute")(run=run, run_dir=run_dir, sim_speed=spec["sim_speed"])
        except Exception as exc:
            transcript.write(traceback.format_exc())
            raise RunFailed(f"attempt {attempt}: {type(exc).__name__}: {exc}"[:2000]) from None
        if not isinstance(values, dict):
            raise RunFailed(f"attempt {attempt}: execute gave {type(values).__name__}, not a dict of values")
        try:
            json.dumps(values)
        except (TypeError, ValueError) as exc:
            raise RunFailed(f"attempt {attempt}: execute's values cannot be written as JSON: {exc}") from None
    return {"run": run, "seconds": time.monotonic() - started, "attempt": attempt, "host": socket.gethostname(),
            "values": values}


def _takes(function: Callable[..., Any], name: str) -> bool:
    """Whether a hook takes the keyword `name` (hooks written before it was offered do not)."""
    try:
        parameters = inspect.signature(function).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters)


# ---------------------------------------------------------------------------------------------
# The summary


def summary_rows(campaign: Campaign, log: RunLog) -> list[dict[str, Any]]:
    """One row per run of the campaign, in the file's order; runs not finished yet are `pending`."""
    records = {RunLog.key(record["run"]): record for record in log.runs()}
    rows = []
    for run in campaign.runs:
        record = records.get(RunLog.key(run))
        row: dict[str, Any] = {"run": run_name(run), **{key: run[key] for key in run}}
        if record is None:
            row["status"] = "pending"
        else:
            row["status"] = "error" if "error" in record else "ok"
            row["attempts"] = record.get("attempts")
            row["seconds"] = record.get("seconds")
            row["host"] = record.get("host")
        values = (record or {}).get("values", {})
        for column in [*campaign.collect, *(k for k in values if k not in campaign.collect)]:
            row[column] = values.get(column)
        row["error"] = (record or {}).get("error", "")
        rows.append(row)
    return rows


def write_summary(campaign: Campaign, log: RunLog, out: Path) -> None:
    rows = summary_rows(campaign, log)
    columns: list[str] = []
    for row in rows:
        columns += [key for key in row if key not in columns]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out / "summary.csv", text.getvalue())
    write_atomic(out / "summary.json", json.dumps({"campaign": campaign.name, "settings": campaign.settings,
                                                       "runs": rows}, indent=2) + "\n")

    def cell(value: Any) -> str:   # a long value (an execute hook's records) in full in the csv and json
        text = "" if value is None else str(value).replace("|", "\\|").replace("\n", " ")
        return text if len(text) <= 120 else text[:117] + "..."

    table = [f"# Campaign {campaign.name}", "",
             "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    table += ["| " + " | ".join(cell(row.get(column)) for column in columns) + " |" for row in rows]
    write_atomic(out / "summary.md", "\n".join(table) + "\n")
    if campaign.report:
        write_atomic(out / "report.md", campaign_report(campaign, log) + "\n")


def campaign_report(campaign: Campaign, log: RunLog) -> str:
    """The campaign's own summary (its `report` hook) of the runs finished so far."""
    if not campaign.report:
        return ""
    records = [record for record in log.runs() if "error" not in record]
    return str(hook(campaign.report, "report")(records))


# ---------------------------------------------------------------------------------------------
# Progress


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


class Progress:
    """Runs done, running, failed and the time left: a bar redrawn in a terminal, lines otherwise."""

    def __init__(self, total: int, already: int, stream=None):
        self.total, self.already = total, already
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty()
        self.started = time.monotonic()
        self.last = ""

    def show(self, done: int, running: int, failed: int) -> None:
        finished = done + failed
        left_runs = self.total - self.already - finished
        elapsed = time.monotonic() - self.started
        eta = "?" if finished == 0 else _duration(elapsed / finished * left_runs)
        text = f"{self.already + done}/{self.total} done, {running} running, {failed} failed, {eta} left"
        if self.tty:
            width = 24
            filled = int(width * (self.already + finished) / max(1, self.total))
            self.stream.write(f"\r\x1b[K[{'#' * filled}{'.' * (width - filled)}] {text}")
            self.stream.flush()
        elif text.split(",")[:3] != self.last.split(",")[:3]:   # a line when a count changes
            print(f"campaign: {text}", file=self.stream, flush=True)
        self.last = text

    def say(self, line: str) -> None:
        if self.tty:
            self.stream.write("\r\x1b[K")
        print(line, file=self.stream, flush=True)   # the bar is drawn again at the next show()

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# ---------------------------------------------------------------------------------------------
# The campaign on Dask


def _open_client(workers: int | None, scheduler: str | None):
    """A Dask client: a LocalCluster of `workers` processes, or the scheduler at `scheduler`."""
    from distributed import Client, LocalCluster
    if scheduler:
        return Client(scheduler), None
    cluster = LocalCluster(n_workers=workers or 1, threads_per_worker=1, processes=True,
                           resources={"servers": 1}, dashboard_address=None)
    return Client(cluster), cluster


def run_campaign(campaign: Campaign, out: Path, workers: int | None = None, scheduler: str | None = None,
                 say: Callable[[str], None] | None = None) -> int:
    """Run what is left of the campaign; EXIT_OK when every run is done."""
    from distributed import wait
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    log = RunLog(out / RESULTS_FILE, campaign.settings)
    todo = log.todo(campaign.runs)
    write_summary(campaign, log, out)
    progress = Progress(len(campaign.runs), len(campaign.runs) - len(todo))
    say = say or progress.say
    if not todo:
        say(f"campaign {campaign.name}: all {len(campaign.runs)} runs done already; summary in {out}")
        return EXIT_OK
    say(f"campaign {campaign.name}: {len(todo)} of {len(campaign.runs)} runs to do, results in {out}")
    client, cluster = _open_client(workers, scheduler)
    failed = done = 0
    try:
        if scheduler and _slots(client) == 0:
            say("no worker of the scheduler has the resource `servers` yet: runs wait for one started with "
                "`dask worker ADDRESS --resources servers=1 --nthreads 1`")
        futures = {}
        for run in todo:
            name = run_name(run)
            spec = {"run": run, "name": name, "run_dir": str(out / "runs" / name),
                    "mission_text": campaign.mission_text,
                    "mission_name": campaign.mission_name, "world": campaign.world, "collect": campaign.collect,
                    "sim_speed": campaign.sim_speed, "timeout_s": campaign.timeout_s, "score": campaign.score,
                    "execute": campaign.execute}
            future = client.submit(execute_run, spec, key=f"rvs-run-{name}-{time.time_ns()}", pure=False,
                                   resources={"servers": 1}, retries=1)
            futures[future] = (run, time.monotonic())
        pending = set(futures)
        while pending:
            progress.show(done, _running(client, pending), failed)
            finished, pending = _wait_some(wait, pending)
            for future in finished:
                run, submitted = futures[future]
                result, error = None, None
                if future.status == "finished":
                    result = future.result()
                    if not isinstance(result, dict) or result.get("run") != run or "values" not in result:
                        error = f"the run returned no result: {result!r}"[:300]   # the run's own check
                else:
                    try:
                        exception = future.exception()
                    except BaseException as lost:   # cancelled: the scheduler gave it up
                        exception = lost
                    error = f"{type(exception).__name__}: {exception}"
                attempts = _attempts(out / "runs" / run_name(run))
                if error is None:
                    log.append(run, result["seconds"], attempts=attempts, host=result["host"], values=result["values"])
                    done += 1
                else:
                    log.append(run, time.monotonic() - submitted, attempts=attempts, error=error)
                    failed += 1
                    say(f"run {run_name(run)} FAILED after {attempts} attempt(s): {error}")
                write_summary(campaign, log, out)
        progress.show(done, 0, failed)
    finally:
        progress.close()
        client.close()
        if cluster is not None:
            cluster.close()
    say(f"campaign {campaign.name}: {done} run(s) done now, {failed} failed; summary in {out}/summary.md")
    return EXIT_OK if failed == 0 else EXIT_FAILED


def _wait_some(wait, pending):
    try:
        result = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
        return result.done, result.not_done
    except TimeoutError:
        return set(), pending


def _running(client, pending) -> int:
    """How many of our runs a worker is executing now (with servers=1 per worker: one per worker)."""
    try:
        keys = {future.key for future in pending}
        assigned = sum(1 for tasks in client.processing().values() for key in tasks if key in keys)
        return min(assigned, _slots(client))   # a worker may hold tasks that wait for its one `servers`
    except Exception:   # the scheduler did not answer: the count is cosmetic
        return 0


def _slots(client) -> int:
    """Servers the cluster may run at once: the sum of its workers' `servers` resources."""
    workers = client.scheduler_info().get("workers", {}).values()
    return int(sum(worker.get("resources", {}).get("servers", 0) for worker in workers))


def _attempts(run_dir: Path) -> int:
    return sum(1 for _ in run_dir.glob("attempt-*"))


# ---------------------------------------------------------------------------------------------
# Command line (`rvs campaign`, wired in clients/cli.py)


def add_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("campaign", help="run a campaign file on Dask (one server per run)")
    parser.add_argument("file", metavar="FILE", help="the campaign (TOML)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="worker processes of a LocalCluster on this machine (default: the CPU count)")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler (tcp://HOST:8786) instead of a LocalCluster")
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="results, summary and the runs' directories (default: ./campaign-NAME)")


def command_campaign(args: argparse.Namespace) -> int:
    def warn(message: str) -> None:
        print(f"rvs: {message}", file=sys.stderr, flush=True)

    try:
        campaign = load_campaign(args.file)
    except CampaignError as exc:
        warn(str(exc))
        return EXIT_NOT_STARTED
    try:
        import distributed  # noqa: F401
    except ImportError:
        warn("rvs campaign needs Dask: pip install -e '.[cluster]'")
        return EXIT_NOT_STARTED
    if args.workers is not None and args.workers < 1:
        warn("--workers must be 1 or more")
        return EXIT_NOT_STARTED
    workers = args.workers or (None if args.scheduler else max(1, os.cpu_count() or 1))
    out = Path(args.out or f"campaign-{campaign.name}")
    return run_campaign(campaign, out, workers=workers, scheduler=args.scheduler)
