"""The RVS text protocol: command-line grammar and reply framing (PROTOCOL.md, version 1).

Pure functions and small value types, no I/O: the server's transports and every client use this
module, so both ends split, quote and frame lines the same way.

    [@TAG] COMMAND [POSITIONAL ...] [--OPTION VALUE | --FLAG | --no-FLAG] ...
    TAG OK [key=value ...]
    TAG ERR CODE REASON MESSAGE
    TAG PROGRESS PERCENT MESSAGE
    * EVENT TOPIC key=value ...
"""
from __future__ import annotations

import re
import shlex
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 8192
LINE_END = "\r\n"  # what the server sends; it accepts LF or CRLF

TAG_RE = re.compile(r"[A-Za-z0-9_.-]{1,32}")
SAFE_NAME_RE = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}")
_KEY_RE = re.compile(r"[A-Za-z0-9_.-]+")
_BARE_VALUE_RE = re.compile(r'[^\s"\\]+')
EVENT_TOPICS = ("mode", "progress", "product", "hazard", "track", "log", "navigate", "guard")

# code -> the reasons PROTOCOL.md pairs with it
ERROR_REASONS: dict[str, int] = {
    "bad-request": 400,
    "line-too-long": 400,
    "bad-encoding": 400,
    "unauthorized": 401,
    "unknown-command": 404,
    "busy": 409,
    "wrong-mode": 409,
    "sleeping": 423,
    "interrupted": 499,
    "internal": 500,
    "device": 503,
    "timeout": 504,
    "storage": 507,
}


class RvsError(Exception):
    """An error that becomes one `ERR CODE REASON MESSAGE` reply."""

    reason = "internal"

    def __init__(self, message: str, reason: str | None = None, data: Mapping[str, Any] | None = None):
        super().__init__(message)
        if reason is not None:
            self.reason = reason
        if self.reason not in ERROR_REASONS:
            raise ValueError(f"unknown error reason {self.reason!r}")
        self.message = message
        self.data = dict(data or {})

    @property
    def code(self) -> int:
        return ERROR_REASONS[self.reason]


class BadRequest(RvsError):
    reason = "bad-request"


class Unauthorized(RvsError):
    reason = "unauthorized"


class UnknownCommand(RvsError):
    reason = "unknown-command"


class Busy(RvsError):
    reason = "busy"


class WrongMode(RvsError):
    reason = "wrong-mode"


class Sleeping(RvsError):
    reason = "sleeping"


class Interrupted(RvsError):
    reason = "interrupted"


class DeviceError(RvsError):
    reason = "device"


class Timeout(RvsError):
    reason = "timeout"


class InternalError(RvsError):
    reason = "internal"


class StorageFull(RvsError):
    """The disk (or the configured storage cap) is full: the job stopped, its recovery set is kept."""

    reason = "storage"


# ---------------------------------------------------------------------------------------------
# Requests


@dataclass(frozen=True)
class CommandLine:
    """A command line split into its parts; option values are still text (None for a bare flag)."""

    tag: str | None
    command: str
    tokens: tuple[str, ...]  # everything after the command name, as split by shlex

    @property
    def text(self) -> str:
        return " ".join([self.command, *(quote_token(t) for t in self.tokens)])


def split_tag(line: str) -> tuple[str | None, str]:
    """Take a leading `@TAG` off a line; the tag is None when there is none or it is malformed."""
    stripped = line.lstrip()
    if not stripped.startswith("@"):
        return None, line
    head, _, rest = stripped[1:].partition(" ")
    head = head.rstrip("\t")
    if TAG_RE.fullmatch(head):
        return head, rest
    return None, line


def is_ignored(line: str) -> bool:
    """Blank lines and `#` comments get no reply and no tag number."""
    stripped = line.strip()
    return not stripped or stripped.startswith("#")


def parse_line(line: str) -> CommandLine:
    """Split one command line; raises BadRequest naming what is wrong."""
    stripped = line.strip()
    if stripped.startswith("@"):
        tag, rest = split_tag(stripped)
        if tag is None:
            bad = stripped[1:].split(None, 1)[0] if stripped[1:].strip() else ""
            raise BadRequest(f"tag {bad!r} is not 1 to 32 characters of [A-Za-z0-9_.-]")
    else:
        tag, rest = None, stripped
    try:
        parts = shlex.split(rest, comments=False, posix=True)
    except ValueError as exc:  # unbalanced quotes, trailing backslash
        raise BadRequest(f"cannot split the line: {exc}") from None
    if not parts:
        raise BadRequest("a command is missing after the tag")
    command = parts[0]
    if command.startswith("-"):
        raise BadRequest(f"expected a command name, got option {command!r}")
    return CommandLine(tag=tag, command=command.lower(), tokens=tuple(parts[1:]))


def quote_token(token: str) -> str:
    """Quote a token so that shlex splits it back to the same string."""
    return token if token and _BARE_VALUE_RE.fullmatch(token) and "'" not in token else shlex.quote(token)


def option_name(field_name: str) -> str:
    """`speed` -> `--speed`; a field named after a Python keyword (`from_`) is `--from`. The one rule
    for the server's parser, its help and the clients' build_line."""
    return "--" + field_name.rstrip("_").replace("_", "-")


def build_line(command: str, positionals: Iterable[Any] = (), options: Mapping[str, Any] | None = None,
               tag: str | None = None) -> str:
    """Compose a command line from parts (used by clients that call commands by name)."""
    words = [f"@{tag}"] if tag else []
    words.append(command)
    words.extend(quote_token(format_value(v)) for v in positionals)
    for name, value in (options or {}).items():
        flag = option_name(name)
        if value is True:
            words.append(flag)
        elif value is False:
            words.append("--no-" + flag[2:])
        elif value is not None:
            words.extend([flag, quote_token(format_value(value))])
    return " ".join(words)


# ---------------------------------------------------------------------------------------------
# Values: ranges, points, names


def parse_range(text: str) -> tuple[float, float]:
    """`A:B` -> (A, B)."""
    parts = str(text).split(":")
    if len(parts) != 2:
        raise ValueError(f"expected a range A:B, got {text!r}")
    try:
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"expected a range of two numbers A:B, got {text!r}") from None


def parse_point(text: str) -> tuple[float, float]:
    """`X,Y` -> (X, Y)."""
    parts = str(text).split(",")
    if len(parts) != 2:
        raise ValueError(f"expected a point X,Y, got {text!r}")
    try:
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"expected a point of two numbers X,Y, got {text!r}") from None


def check_safe_name(name: str) -> str:
    """Client-given names are names, not paths: [A-Za-z0-9._-], no leading dot."""
    if not isinstance(name, str) or not SAFE_NAME_RE.fullmatch(name):
        raise ValueError(
            f"{name!r} is not a safe name: 1 to 128 characters of [A-Za-z0-9._-], not starting with a dot")
    return name


def format_value(value: Any) -> str:
    """The text of one value: floats with enough digits, tuples as X,Y, booleans as 1/0."""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (tuple, list)):
        return ",".join(format_value(v) for v in value)
    if value is None:
        return "none"
    return str(value)


def quote_value(text: str) -> str:
    """A reply value: bare when it can be, otherwise double-quoted with backslash escapes."""
    if text and _BARE_VALUE_RE.fullmatch(text):
        return text
    escaped = (text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
               .replace("\r", "\\r").replace("\t", "\\t"))
    return f'"{escaped}"'


def format_pairs(data: Mapping[str, Any]) -> str:
    return " ".join(f"{key}={quote_value(format_value(value))}" for key, value in data.items())


def parse_pairs(text: str) -> dict[str, str]:
    """Inverse of format_pairs: `a=1 b="x y"` -> {'a': '1', 'b': 'x y'}."""
    pairs: dict[str, str] = {}
    i, n = 0, len(text)
    while i < n:
        while i < n and text[i] == " ":
            i += 1
        if i >= n:
            break
        eq = text.find("=", i)
        if eq < 0:
            raise ValueError(f"expected key=value at {text[i:]!r}")
        key = text[i:eq]
        if not _KEY_RE.fullmatch(key):
            raise ValueError(f"bad key {key!r}")
        i = eq + 1
        if i < n and text[i] == '"':
            i += 1
            out = []
            while i < n and text[i] != '"':
                if text[i] == "\\" and i + 1 < n:
                    i += 1
                    out.append({"n": "\n", "r": "\r", "t": "\t"}.get(text[i], text[i]))
                else:
                    out.append(text[i])
                i += 1
            if i >= n:
                raise ValueError("unterminated quoted value")
            i += 1
            pairs[key] = "".join(out)
        else:
            end = text.find(" ", i)
            end = n if end < 0 else end
            pairs[key] = text[i:end]
            i = end
    return pairs


# ---------------------------------------------------------------------------------------------
# Replies


def _clean_message(message: str) -> str:
    """Messages are the rest of one line: no line breaks may leak into them."""
    return " ".join(str(message).split()) or "-"


def format_ok(tag: str, data: Mapping[str, Any] | None = None) -> str:
    pairs = format_pairs(data or {})
    return f"{tag} OK {pairs}" if pairs else f"{tag} OK"


def format_err(tag: str, code: int, reason: str, message: str) -> str:
    return f"{tag} ERR {code} {reason} {_clean_message(message)}"


def format_error(tag: str, error: RvsError) -> str:
    return format_err(tag, error.code, error.reason, error.message)


def format_progress(tag: str, percent: float, message: str) -> str:
    return f"{tag} PROGRESS {int(max(0, min(100, round(percent))))} {_clean_message(message)}"


def format_event(topic: str, data: Mapping[str, Any]) -> str:
    pairs = format_pairs(data)
    return f"* EVENT {topic} {pairs}" if pairs else f"* EVENT {topic}"


@dataclass
class Reply:
    """One line from the server, parsed."""

    kind: str  # "ok" | "err" | "progress" | "event" | "greeting"
    tag: str | None = None
    data: dict[str, str] = field(default_factory=dict)
    code: int = 200
    reason: str = "ok"
    message: str = ""
    percent: int | None = None
    topic: str | None = None

    @property
    def final(self) -> bool:
        return self.kind in ("ok", "err")


def parse_reply(line: str) -> Reply:
    """Parse any line the server sends; raises ValueError for a line that follows no form."""
    line = line.rstrip("\r\n")
    if line.startswith("* EVENT "):
        topic, _, rest = line[len("* EVENT "):].partition(" ")
        return Reply(kind="event", topic=topic, data=parse_pairs(rest))
    if line.startswith("RVS "):
        parts = line.split()
        return Reply(kind="greeting", data={"version": parts[1] if len(parts) > 1 else "",
                                            "mode": parts[2] if len(parts) > 2 else ""})
    tag, _, rest = line.partition(" ")
    word, _, rest = rest.partition(" ")
    if word == "OK":
        return Reply(kind="ok", tag=tag, data=parse_pairs(rest))
    if word == "ERR":
        code, _, rest = rest.partition(" ")
        reason, _, message = rest.partition(" ")
        return Reply(kind="err", tag=tag, code=int(code), reason=reason, message=message)
    if word == "PROGRESS":
        percent, _, message = rest.partition(" ")
        return Reply(kind="progress", tag=tag, percent=int(percent), message=message)
    raise ValueError(f"not an RVS reply line: {line!r}")
