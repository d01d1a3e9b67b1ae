"""The mission runner: plays a mission file against the server (PROTOCOL.md, "Mission files").

A mission file is what an operator would type in telnet: one command a line, `#` comments and blank
lines skipped. `${NAME}` is replaced by the value of `--set NAME=VALUE` (as text, like make: a value
with spaces becomes several words); an unset name is an error before anything is sent. A line that
starts with `-` may fail: its failure is reported and the mission goes on. Any other `ERR` stops
the mission.

`run` sends each line and prints every reply; `check` sends each line as `check LINE` and nothing
else, so nothing moves, and reports every problem with its line number (a `-` line's problem is
reported but, as when running, does not fail the check).

Exit status: 0 the mission completed (or checked) without an unexcused error; 1 it did not;
2 it could not start (unreadable file, bad --set, unset variable, no connection).

Parsing and substitution are pure functions (parse_mission, substitute, parse_assignments); the
runner takes any client with `stream(line)` (gnc.RvsClient or gnc.ZmqClient).
"""
from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

from rvs_server.protocol import is_ignored, split_tag

from .gnc import Item, RvsClientError, RvsRequestError

EXIT_OK, EXIT_FAILED, EXIT_NOT_STARTED = 0, 1, 2

_REFERENCE_RE = re.compile(r"\$\{([^}]*)(\}?)")  # group 2 is empty when the brace is never closed
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class MissionError(Exception):
    """A mission that cannot be run as written; `problems` are `line N: ...` sentences."""

    def __init__(self, problems: list[str]):
        super().__init__("; ".join(problems))
        self.problems = problems


@dataclass(frozen=True)
class MissionLine:
    """One command of a mission, ready to send."""

    number: int  # line number in the file, from 1
    command: str  # after substitution, without the leading `-`
    excused: bool  # the line started with `-`: its failure does not stop the mission


# ---------------------------------------------------------------------------------------------
# Pure parts: assignments, substitution, parsing


def parse_assignments(items: Iterable[str]) -> dict[str, str]:
    """`["PAN=30", "TILT=-5"]` -> {"PAN": "30", "TILT": "-5"}; a malformed item raises MissionError."""
    variables: dict[str, str] = {}
    problems = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not _NAME_RE.fullmatch(name):
            problems.append(f"--set {item!r}: expected NAME=VALUE with NAME of [A-Za-z0-9_], not starting "
                            f"with a digit")
        else:
            variables[name] = value
    if problems:
        raise MissionError(problems)
    return variables


def reference_problems(text: str, variables: Mapping[str, str], number: int) -> list[str]:
    """What is wrong with the `${...}` references of one line (empty when nothing is)."""
    problems = []
    for match in _REFERENCE_RE.finditer(text):
        name, closed = match.group(1), match.group(2)
        if not closed:
            problems.append(f"line {number}: unterminated ${{ in {text.strip()!r}")
        elif not _NAME_RE.fullmatch(name):
            problems.append(f"line {number}: bad variable name ${{{name}}}")
        elif name not in variables:
            problems.append(f"line {number}: variable {name} is not set (give --set {name}=VALUE)")
    return problems


def substitute(text: str, variables: Mapping[str, str], number: int = 0) -> str:
    """Replace every `${NAME}`; raises MissionError naming the line and the variable."""
    problems = reference_problems(text, variables, number)
    if problems:
        raise MissionError(problems)
    return _REFERENCE_RE.sub(lambda match: variables[match.group(1)], text)


def parse_mission(text: str, variables: Mapping[str, str]) -> list[MissionLine]:
    """All commands of a mission file, substituted; every problem of the file in one MissionError."""
    lines: list[MissionLine] = []
    problems: list[str] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        if is_ignored(raw):
            continue  # comments are not substituted: an unset name in a comment is no error
        stripped = raw.strip()
        excused = stripped.startswith("-")
        command = stripped[1:].strip() if excused else stripped
        if is_ignored(command):
            problems.append(f"line {number}: no command after '-'")
            continue
        line_problems = reference_problems(command, variables, number)
        if line_problems:
            problems.extend(line_problems)
            continue
        lines.append(MissionLine(number, substitute(command, variables, number), excused))
    if problems:
        raise MissionError(problems)
    return lines


def unused_variables(text: str, variables: Mapping[str, str]) -> list[str]:
    """Names given with --set that the mission never uses (most often a typo)."""
    used = {match.group(1) for match in _REFERENCE_RE.finditer(text)}
    return [name for name in variables if name not in used]


def check_line(command: str) -> str:
    """`check COMMAND`, keeping the command's own `@TAG` in front where the server expects it."""
    tag, rest = split_tag(command)
    return f"@{tag} check {rest.strip()}" if tag else f"check {command}"


# ---------------------------------------------------------------------------------------------
# Running and checking


class Client(Protocol):
    def stream(self, line: str) -> Iterable[Item]: ...


@dataclass
class MissionReport:
    """What happened, for the summary and the exit status."""

    total: int  # commands in the mission
    sent: int = 0
    ok: int = 0
    excused: list[int] = field(default_factory=list)  # line numbers of excused failures
    failures: list[int] = field(default_factory=list)  # line numbers of unexcused failures
    stopped_at: int | None = None  # the line the mission stopped at (run) or None

    @property
    def exit_status(self) -> int:
        return EXIT_FAILED if self.failures else EXIT_OK


def _as_written(line: MissionLine) -> str:
    return f"- {line.command}" if line.excused else line.command


def _play(client: Client, line: str, out: Callable[[str], None]) -> RvsRequestError | None:
    """Send one line, print every reply as it comes; the ERR, if it failed."""
    try:
        for item in client.stream(line):
            out(item.line)
    except RvsRequestError as error:
        out(error.line)
        return error
    return None


def run_mission(client: Client, lines: list[MissionLine], out: Callable[[str], None]) -> MissionReport:
    """Send each line; stop at the first ERR of a line without `-`, or when the connection fails."""
    return _walk(client, lines, out, checking=False)


def check_mission(client: Client, lines: list[MissionLine], out: Callable[[str], None]) -> MissionReport:
    """Send `check LINE` for every line (and nothing else); report every problem with its line."""
    return _walk(client, lines, out, checking=True)


def _walk(client: Client, lines: list[MissionLine], out: Callable[[str], None], checking: bool) -> MissionReport:
    """Play the lines in order. A run stops at the first unexcused failure; a check goes on, so
    that it reports every problem at once."""
    report = MissionReport(total=len(lines))
    failed = "would fail" if checking else "failed"
    for line in lines:
        if checking:
            out(f"line {line.number}: check {line.command}{'  (excused by -)' if line.excused else ''}")
        else:
            out(f"line {line.number}: {_as_written(line)}")
        report.sent += 1
        try:
            error = _play(client, check_line(line.command) if checking else line.command, out)
        except RvsClientError as exc:  # no connection, no reply: nothing after this can run
            out(f"line {line.number}: {exc}; {'check' if checking else 'mission'} stopped")
            report.failures.append(line.number)
            report.stopped_at = line.number
            return report
        if error is None:
            report.ok += 1
        elif line.excused:
            going_on = "" if checking else "; going on"
            out(f"line {line.number}: {failed} ({error.code} {error.reason}), excused by '-'{going_on}")
            report.excused.append(line.number)
        else:
            out(f"line {line.number}: {failed} ({error.code} {error.reason})"
                + ("" if checking else "; mission stopped"))
            report.failures.append(line.number)
            if not checking:
                report.stopped_at = line.number
                return report
    return report


def _plural(count: int, word: str) -> str:
    return f"{count} {word}" if count == 1 else f"{count} {word}s"


def _line_list(numbers: list[int]) -> str:
    return f" (line {', '.join(str(n) for n in numbers)})" if numbers else ""


def summary(name: str, report: MissionReport, checking: bool = False) -> str:
    """One paragraph saying how the mission went."""
    verb = "checked" if checking else "sent"
    counts = (f"{_plural(report.sent, 'line')} of {report.total} {verb}, {report.ok} OK, "
              f"{_plural(len(report.excused), 'excused failure')}{_line_list(report.excused)}")
    if checking:
        problems = _plural(len(report.failures), "problem")
        verdict = "well-formed" if not report.failures else f"NOT well-formed: {problems}{_line_list(report.failures)}"
        if report.stopped_at is not None:
            verdict = f"check STOPPED at line {report.stopped_at}"
        return f"mission {name}: {verdict}; {counts}"
    if report.stopped_at is not None:
        return (f"mission {name}: STOPPED at line {report.stopped_at}; {counts}; "
                f"{_plural(report.total - report.sent, 'line')} not run")
    return f"mission {name}: completed; {counts}"


def load_mission(path: str, assignments: Iterable[str]) -> tuple[str, list[MissionLine], list[str]]:
    """Read and parse a file: (text, lines, names given but unused); raises MissionError or OSError."""
    variables = parse_assignments(assignments)
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    return text, parse_mission(text, variables), unused_variables(text, variables)


__all__ = ["MissionLine", "MissionError", "MissionReport", "parse_assignments", "substitute", "parse_mission",
           "reference_problems", "unused_variables", "check_line", "run_mission", "check_mission", "summary",
           "load_mission", "EXIT_OK", "EXIT_FAILED", "EXIT_NOT_STARTED"]
