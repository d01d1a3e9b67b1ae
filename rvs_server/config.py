"""Configuration: pydantic base classes, the TOML loader, and command-line binding.

A command's options are the fields of its Config class. The same class gives the defaults (from the
code, then from the module's TOML file), validates every invocation from any transport, and
generates `help`, so options, checks and documentation cannot drift apart.
"""
from __future__ import annotations

import difflib
import tomllib
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Generic, Literal, TypeVar

import annotated_types
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from pydantic.fields import FieldInfo

from .protocol import BadRequest, check_safe_name, format_value, option_name, parse_point, parse_range


@dataclass(frozen=True)
class TypeLabel:
    """How `help` names a type whose Python annotation says too little (a range, a point)."""

    text: str


def _range(value: Any) -> Any:
    if isinstance(value, str):
        return parse_range(value)
    return value


def _point(value: Any) -> Any:
    if isinstance(value, str):
        return parse_point(value)
    return value


def _ordered(value: tuple[float, float]) -> tuple[float, float]:
    if value[0] > value[1]:
        raise ValueError(f"range start {value[0]:g} is greater than its end {value[1]:g}")
    return value


Range = Annotated[tuple[float, float], BeforeValidator(_range), AfterValidator(_ordered), TypeLabel("range A:B")]
Point = Annotated[tuple[float, float], BeforeValidator(_point), TypeLabel("point X,Y")]
SafeName = Annotated[str, AfterValidator(check_safe_name), TypeLabel("name")]


class ConfigError(Exception):
    """A configuration file that cannot be used; the message names file, field, value and rule."""


class Settings(BaseModel):
    """Base of every configuration model: unknown keys are errors, not silently ignored."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, frozen=False)


class CommandConfig(Settings):
    """Base of a command's options. Field names are option names with underscores for dashes."""


# ---------------------------------------------------------------------------------------------
# Describing fields: used by error messages and by `help`


def _metadata(info: FieldInfo) -> list[Any]:
    meta = list(info.metadata)
    annotation = info.annotation
    if typing.get_origin(annotation) is Annotated:
        meta.extend(typing.get_args(annotation)[1:])
    return meta


def _unwrap_optional(annotation: Any) -> tuple[Any, bool]:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, getattr(__import__("types"), "UnionType", None)) \
            and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return (rest[0] if len(rest) == 1 else annotation), True
    return annotation, False


def type_label(info: FieldInfo) -> str:
    for item in _metadata(info):
        if isinstance(item, TypeLabel):
            return item.text
    annotation, _ = _unwrap_optional(info.annotation)
    if typing.get_origin(annotation) is Annotated:
        for item in typing.get_args(annotation)[1:]:
            if isinstance(item, TypeLabel):
                return item.text
        annotation = typing.get_args(annotation)[0]
    if typing.get_origin(annotation) is Literal:
        return "one of " + "|".join(str(a) for a in typing.get_args(annotation))
    if annotation is bool:
        return "flag"
    if annotation in (int, float, str):
        return {int: "int", float: "float", str: "text"}[annotation]
    if isinstance(annotation, type) and issubclass(annotation, Path):
        return "path"
    # A parametrised generic model (PerSensor[float]) is named by its generic class.
    annotation = (getattr(annotation, "__pydantic_generic_metadata__", None) or {}).get("origin") or annotation
    return getattr(annotation, "__name__", str(annotation))


def allowed_range(info: FieldInfo) -> str:
    """The bounds of a numeric field as text, e.g. `0.1..150` or `> 0`; empty when unbounded."""
    lo: Any = None
    hi: Any = None
    lo_open = hi_open = False
    for item in _metadata(info):
        if isinstance(item, annotated_types.Ge):
            lo = item.ge
        elif isinstance(item, annotated_types.Gt):
            lo, lo_open = item.gt, True
        elif isinstance(item, annotated_types.Le):
            hi = item.le
        elif isinstance(item, annotated_types.Lt):
            hi, hi_open = item.lt, True
        elif isinstance(item, annotated_types.Interval):
            if item.ge is not None:
                lo = item.ge
            if item.gt is not None:
                lo, lo_open = item.gt, True
            if item.le is not None:
                hi = item.le
            if item.lt is not None:
                hi, hi_open = item.lt, True
    if lo is not None and hi is not None and not lo_open and not hi_open:
        return f"{format_value(lo)}..{format_value(hi)}"
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {format_value(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {format_value(hi)}")
    return " and ".join(parts)


def describe_allowed(info: FieldInfo) -> str:
    """What a field accepts: its type and, when bounded, its range."""
    label = type_label(info)
    bounds = allowed_range(info)
    return f"{label} {bounds}" if bounds else label


def describe_default(info: FieldInfo) -> str:
    if info.is_required():
        return "required"
    default = info.get_default(call_default_factory=True)
    return "none" if default is None else format_value(default)


def _dotted(loc: tuple[int | str, ...]) -> str:
    return ".".join(str(p) for p in loc)


def describe_validation_error(exc: ValidationError, model: type[BaseModel], where: str,
                              name_of: Callable[[tuple[int | str, ...]], str] = _dotted) -> str:
    """One sentence per problem: where, the field, the value, what is wrong and what is allowed."""
    problems = []
    for err in exc.errors(include_url=False):
        loc = err.get("loc", ())
        info = _field_at(model, loc)
        value = err.get("input")
        text = f"{name_of(loc) or 'value'}"
        if err.get("type") != "missing" and err.get("type") != "extra_forbidden":
            text += f" = {value!r}"
        msg = err.get("msg", "invalid").removeprefix("Value error, ")
        text += f": {msg}"
        if err.get("type") == "extra_forbidden":
            text = f"{name_of(loc)}: unknown field"
            owner, parent = _owner_at(model, loc)   # a nested table names its own fields
            allowed = ", ".join(name_of((*parent, n)) for n in owner.model_fields)
            close = difflib.get_close_matches(str(loc[-1]), list(owner.model_fields), n=1)
            text += f" (did you mean {name_of((*parent, close[0]))}?)" if close else ""
            text += f"; allowed: {allowed}" if allowed else ""
        elif info is not None:
            text += f"; allowed: {describe_allowed(info)}"
        problems.append(text)
    return f"{where}: " + "; ".join(problems)


def _owner_at(model: type[BaseModel], loc: tuple) -> tuple[type[BaseModel], tuple]:
    """The model whose field loc's last part would be, and the path to it."""
    for depth in range(len(loc) - 1, 0, -1):
        info = _field_at(model, loc[:depth])
        annotation = _unwrap_optional(info.annotation)[0] if info is not None else None
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            return annotation, tuple(loc[:depth])
    return model, ()


def _field_at(model: type[BaseModel], loc: tuple) -> FieldInfo | None:
    current: Any = model
    info = None
    for part in loc:
        if isinstance(current, type) and issubclass(current, BaseModel) and part in current.model_fields:
            info = current.model_fields[part]
            annotation, _ = _unwrap_optional(info.annotation)
            current = annotation
        else:
            break
    return info


# ---------------------------------------------------------------------------------------------
# Files


def read_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file; a missing file is an empty one (every field has its code default)."""
    if not path.exists():
        return {}
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None


ModelT = TypeVar("ModelT", bound=BaseModel)


def validate_section(model: type[ModelT], data: Mapping[str, Any], where: str) -> ModelT:
    try:
        return model.model_validate(dict(data))
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(
            exc, model, where, name_of=lambda loc: "field " + ".".join(str(p) for p in loc))) from None


def load_model(path: Path, model: type[ModelT], overrides: Mapping[str, Any] | None = None) -> ModelT:
    """Load one TOML file into a model; values in `overrides` (from the command line) win.

    The file is validated on its own first, so a bad value in it is reported even when the command
    line happens to override it.
    """
    data = read_toml(path)
    validate_section(model, data, str(path))
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    return validate_section(model, {**data, **given}, "command line") if given else validate_section(
        model, data, str(path))


# ---------------------------------------------------------------------------------------------
# Binding a command line to a Config class


def bind_tokens(command: str, tokens: tuple[str, ...] | list[str], config: type[CommandConfig],
                positionals: tuple[str, ...] = ()) -> dict[str, Any]:
    """Turn `POSITIONAL ... --opt VALUE --flag --no-flag` into raw field values for `config`.

    Flags take no value; every other option takes the next token, even one starting with a dash,
    so `--tilt -20` works. `--opt=VALUE` is accepted too.
    """
    fields = config.model_fields
    values: dict[str, Any] = {}
    free: list[str] = []
    i = 0
    while i < len(tokens):
        token = tokens[i]
        i += 1
        if not token.startswith("--") or token == "--":
            if token == "--":  # everything after a bare -- is positional
                free.extend(tokens[i:])
                break
            free.append(token)
            continue
        name, has_value, inline = token[2:].partition("=")
        field_name = name.replace("-", "_")
        if field_name not in fields and field_name + "_" in fields:  # --from binds to from_
            field_name += "_"
        negated = False
        if field_name not in fields and field_name.startswith("no_") and _is_flag(fields.get(field_name[3:])):
            field_name, negated = field_name[3:], True
        if field_name not in fields:
            raise BadRequest(_unknown_option(command, name, config))
        if field_name in values:
            raise BadRequest(f"{command}: {option_name(field_name)} given twice")
        info = fields[field_name]
        if _is_flag(info):
            if has_value:
                values[field_name] = inline
            else:
                values[field_name] = not negated
        elif has_value:
            values[field_name] = inline
        else:
            if i >= len(tokens):
                raise BadRequest(f"{command}: {option_name(field_name)} needs a value "
                                 f"({describe_allowed(info)})")
            values[field_name] = tokens[i]
            i += 1
    if len(free) > len(positionals):
        extra = free[len(positionals)]
        expected = " ".join(p.upper() for p in positionals) or "no positional arguments"
        raise BadRequest(f"{command}: unexpected argument {extra!r}; usage takes {expected}")
    for name, token in zip(positionals, free, strict=False):  # fewer words: the rest keep their defaults
        if name in values:
            raise BadRequest(f"{command}: {name} given twice")
        values[name] = token
    return values


def _is_flag(info: FieldInfo | None) -> bool:
    if info is None:
        return False
    annotation, _ = _unwrap_optional(info.annotation)
    return annotation is bool


def _unknown_option(command: str, name: str, config: type[CommandConfig]) -> str:
    options = [option_name(f) for f in config.model_fields]
    close = difflib.get_close_matches("--" + name, options, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    listed = ", ".join(options) if options else "none"
    return f"{command}: unknown option --{name}{hint} (options: {listed})"


def build_config(command: str, config: type[CommandConfig], defaults: Mapping[str, Any],
                 values: Mapping[str, Any]) -> CommandConfig:
    """Validate an invocation: module-file defaults, overridden by what the client gave."""
    unknown = [k for k in values if k not in config.model_fields]
    if unknown:
        raise BadRequest(_unknown_option(command, unknown[0].replace("_", "-"), config))
    try:
        return config.model_validate({**defaults, **values})
    except ValidationError as exc:
        raise BadRequest(describe_validation_error(
            exc, config, command, name_of=lambda loc: option_name(str(loc[0])) if loc else "value")) from None


# Re-exported for modules: Field with constraints is how options declare their allowed range.
__all__ = ["Field", "Settings", "CommandConfig", "Range", "Point", "SafeName", "ConfigError", "TypeLabel",
           "bind_tokens", "build_config", "load_model", "read_toml", "validate_section",
           "describe_allowed", "describe_default", "type_label", "option_name", "PerSensor"]


T = TypeVar("T")


class PerSensor(BaseModel, Generic[T]):
    """A setting for each mapping sensor; the fused map (TOF and stereo together) takes the TOF's
    unless it has its own."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    tof: T
    stereo: T
    fused: T | None = None

    @model_validator(mode="before")
    @classmethod
    def _one_for_both(cls, value: Any) -> Any:
        """A single value serves both sensors."""
        return value if isinstance(value, (dict, PerSensor)) else {"tof": value, "stereo": value}

    def of(self, sensor: str) -> T:
        if sensor == "fused":
            return self.tof if self.fused is None else self.fused
        return getattr(self, sensor)
