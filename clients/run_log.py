"""A campaign's results kept as they come: one JSON line per finished run, so a campaign that the
clock or a crash stops is continued by running the same command again.

Each line is one run: its `run` (what names it in the campaign: seed, sensor, ...), the campaign's
`settings` (what makes two runs comparable: length, max turn, orient on or off, ...), its scores and
`seconds`. A line is appended, flushed and fsynced the moment its run ends, by the one process that
collects the results, so a campaign killed halfway loses at most the runs still going. A rerun
skips every run whose `run` and `settings` are already in the file; a run that ended in an `error`
is written too (the report shows it) but is not done: the next rerun tries it again.

Reading is tolerant of what a kill can leave: a last line cut short is ignored. The campaign
scripts under tests/bench/ use it now; `rvs campaign` (on Dask) is meant to write the same lines.
"""
from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


def read_runs(path: Path) -> list[dict[str, Any]]:
    """Every whole line of the file (none when it does not exist), in the order they were written."""
    if not path.exists():
        return []
    runs = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            runs.append(json.loads(line))
        except json.JSONDecodeError:   # the last line of a run killed while writing it
            continue
    return runs


def _key(value: Any) -> str:
    """A dict as a hashable, order-free key (JSON with sorted keys: what the file holds round-trips)."""
    return json.dumps(value, sort_keys=True)


@dataclass(frozen=True)
class RunLog:
    """The results file of one campaign `settings`; several settings may share one file."""

    path: Path
    settings: dict[str, Any]

    def runs(self) -> list[dict[str, Any]]:
        """The runs of these settings in the file, errors included, the last line of a run winning."""
        mine = {}
        for record in read_runs(self.path):
            if _key(record.get("settings")) == _key(self.settings):
                mine[_key(record.get("run"))] = record
        return list(mine.values())

    def done(self) -> set[str]:
        """Keys (see `key`) of the runs that finished without an error under these settings."""
        return {_key(record["run"]) for record in self.runs() if "error" not in record}

    @staticmethod
    def key(run: dict[str, Any]) -> str:
        return _key(run)

    def todo(self, runs: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
        """Those of `runs` not yet done under these settings, in their order."""
        done = self.done()
        return [run for run in runs if _key(run) not in done]

    def append(self, run: dict[str, Any], seconds: float, **scores: Any) -> dict[str, Any]:
        """Write one finished run (or one with `error=...`) and make it durable before returning."""
        record = {"run": run, "settings": self.settings, "seconds": round(float(seconds), 3), **scores}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        line = json.dumps(record) + "\n"
        with open(self.path, "a+b") as handle:
            # A kill in the middle of a write leaves a line without its end: start on a line of our own.
            handle.seek(0, os.SEEK_END)
            if handle.tell() > 0:
                handle.seek(-1, os.SEEK_END)
                if handle.read(1) != b"\n":
                    line = "\n" + line
            handle.write(line.encode())
            handle.flush()
            os.fsync(handle.fileno())
        return record


def write_atomic(path: Path, text: str) -> None:
    """Replace `path` with `text` whole or not at all (a summary a kill cuts short is worse than the
    previous one): written beside it, fsynced, renamed over it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "w") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def group_by_settings(records: Iterable[dict[str, Any]]) -> list[tuple[dict[str, Any], list[dict[str, Any]]]]:
    """The file's runs grouped by their settings (first seen first), the last line of a run winning:
    what a `--report` prints one table for."""
    groups: dict[str, tuple[dict[str, Any], dict[str, dict[str, Any]]]] = {}
    for record in records:
        settings = record.get("settings") or {}
        group = groups.setdefault(_key(settings), (settings, {}))
        group[1][_key(record.get("run"))] = record
    return [(settings, list(runs.values())) for settings, runs in groups.values()]


def describe(settings: dict[str, Any]) -> str:
    """`key=value ...` of a settings dict, for a report's heading."""
    return " ".join(f"{key}={value}" for key, value in sorted(settings.items()))


def report(path: Path, summarise: Callable[[list[dict[str, Any]], str], str]) -> str:
    """A results file's summary from the file alone, one block per settings: a heading (the runs and
    their seconds), `summarise(finished runs, sensor)` per sensor (each run's scores with its `run`
    keys merged in), and the runs that broke."""
    records = read_runs(path)
    if not records:
        return f"{path}: no runs"
    blocks = []
    for settings, runs in group_by_settings(records):
        finished = [{**r, **r["run"]} for r in runs if "error" not in r]
        lines = [f"== {describe(settings)}: {len(finished)} runs, {sum(r['seconds'] for r in runs):.0f} s"]
        lines += [summarise(finished, sensor) for sensor in sorted({r["sensor"] for r in finished})]
        lines += [f"  {r['run']['sensor']} seed {r['run']['seed']} broke: {r['error'][:200]}"
                  for r in runs if "error" in r]
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def add_results_options(parser: argparse.ArgumentParser, default: Path) -> None:
    """A campaign script's --results FILE (where its runs are kept) and --report FILE."""
    parser.add_argument("--results", type=Path, default=default, help="the JSON-lines file runs are kept in")
    parser.add_argument("--report", type=Path, metavar="FILE", help="print the summary of this results file and stop")


def reported(args: argparse.Namespace, summarise: Callable[[list[dict[str, Any]], str], str]) -> bool:
    """With --report: print that file's summary (`report`) and say so, for the script to stop."""
    if args.report is None:
        return False
    print(report(args.report, summarise))
    return True


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """A campaign script's --set FILE:KEY=VALUE (repeatable): a setting of the servers' configs/FILE for
    every run, kept in the runs' settings so each choice is a table of its own."""
    parser.add_argument("--set", dest="config_set", action="append", default=[], metavar="FILE:KEY=VALUE",
                        help="a setting of configs/FILE for every run, the value in TOML: orient.toml:"
                             "keyframe_overlap=0.4, navigation.toml:orient={tof=true,stereo=true}; a dotted "
                             "KEY names a table's key")


def config_overrides(items: Iterable[str]) -> dict[str, dict[str, Any]]:
    """{file: {key: value}} of --set items (`FILE:KEY=VALUE`, VALUE a TOML value, KEY dotted for
    tables). ValueError naming the item and what is allowed when one is not of that form."""
    import tomllib

    overrides: dict[str, dict[str, Any]] = {}
    for item in items:
        name, colon, setting = item.partition(":")
        key, equals, text = setting.partition("=")
        if not (colon and equals and name.endswith(".toml") and key.strip()):
            raise ValueError(f"--set {item!r}: expected FILE.toml:KEY=VALUE, e.g. orient.toml:min_matches=40")
        try:
            value = tomllib.loads(f"value = {text.strip()}")["value"]
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"--set {item!r}: the value {text.strip()!r} is not a TOML value ({exc}); "
                             "strings need quotes: sensor='stereo'") from None
        table = overrides.setdefault(name.strip(), {})
        *parents, last = [part.strip() for part in key.split(".")]
        for part in parents:
            table = table.setdefault(part, {})
        table[last] = value
    return overrides
