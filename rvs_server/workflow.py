"""Workflows: processing chains in YAML (the replacement of the original PROX scripts).

A workflow file names its steps in order; each step runs one registered operation with its
parameters and the results of earlier steps:

    name: dem-full-tof
    steps:
      - name: grid
        op: dem.grid_max
        inputs: {points: clean}          # the result of the earlier step `clean`
        params: {cell: $args.cell}       # a command option; $config.NAME reads the module's settings

An operator changes a chain, a threshold or adds a filter step by editing YAML. Before anything
runs, the engine checks the whole file (unknown operation, unknown or missing input, a step used
before it exists, a bad parameter, a reference to an option that does not exist) and refuses it
with the file, the step and the reason. While running it reports PROGRESS per step, checkpoints
each finished step's result into the job's recovery folder, so break, quit or a crash lose at most
the running step, and records provenance (file, hash, resolved parameters, timings) for the
product's manifest.

A step's result is arrays, numbers, strings, GridSpecs, lists, tuples and dicts of them, and the
dataclasses its Operations names with `result_types` (those come back from a checkpoint as
themselves; any other dataclass as a dict of its fields).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from toolbox.grid import GridSpec

from .config import describe_validation_error
from .files import save_npz_atomic, write_text_atomic

if TYPE_CHECKING:
    from rvs_server.jobs import JobContext

# `$args.cell` or `${args.cell}` (the braces need block style in YAML; flow style takes the bare form).
REFERENCE = re.compile(r"^\$(?:\{(args|config)\.([A-Za-z_]\w*)\}|(args|config)\.([A-Za-z_]\w*))$")


def _reference(value: Any) -> tuple[str, str] | None:
    """(`args` or `config`, field name) when a parameter value is a reference, else None."""
    match = REFERENCE.match(value) if isinstance(value, str) else None
    if match is None:
        return None
    return (match.group(1), match.group(2)) if match.group(1) else (match.group(3), match.group(4))
STEP_NAME = re.compile(r"^[a-z][a-z0-9_]{0,40}$")


class WorkflowError(ValueError):
    """A workflow file that cannot run; the message names the file and the step."""


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class StepParams(BaseModel):
    """Base of an operation's parameters: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


# ---------------------------------------------------------------------------------------------
# Operations


@dataclass(frozen=True)
class Operation:
    name: str
    func: Callable[..., Any]  # func(step: StepContext, params, **inputs) -> result
    params: type[BaseModel]
    inputs: tuple[str, ...]
    optional_inputs: tuple[str, ...] = ()
    summary: str = ""


class Operations:
    """The operations workflow steps may name, e.g. `dem.grid_max`."""

    def __init__(self) -> None:
        self.items: dict[str, Operation] = {}
        self.types: dict[str, type] = {}   # dataclasses step results may hold, by type_name

    def result_types(self, *classes: type) -> None:
        """The dataclasses these operations' results hold, each nested one named too, so that a step
        resumed from its checkpoint hands on the same objects as one that ran."""
        for cls in classes:
            if not (dataclasses.is_dataclass(cls) and isinstance(cls, type)):
                raise TypeError(f"{cls!r} is not a dataclass")
            if not all(f.init for f in dataclasses.fields(cls)):
                raise TypeError(f"{cls.__name__} has fields its constructor does not take")
            self.types[type_name(cls)] = cls

    def register(self, name: str, params: type[BaseModel] = NoParams, inputs: tuple[str, ...] = (),
                 optional_inputs: tuple[str, ...] = ()) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        def add(func: Callable[..., Any]) -> Callable[..., Any]:
            if name in self.items:
                raise ValueError(f"operation {name} registered twice")
            summary = (func.__doc__ or "").strip().split("\n")[0]
            self.items[name] = Operation(name, func, params, inputs, optional_inputs, summary)
            return func
        return add

    def get(self, name: str) -> Operation | None:
        return self.items.get(name)


# ---------------------------------------------------------------------------------------------
# Files


@dataclass
class Step:
    name: str
    op: str
    inputs: dict[str, str]      # input name -> earlier step name
    params: dict[str, Any]      # raw, may hold ${args.x} / ${config.x}
    checkpoint: bool = True


@dataclass
class Workflow:
    name: str
    path: Path
    text: str
    steps: list[Step]
    description: str = ""

    @property
    def digest(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()[:16]


def load_workflow(path: Path, operations: Operations, args_model: type[BaseModel] | None = None,
                  config_model: type[BaseModel] | None = None) -> Workflow:
    """Read and check a workflow file; raises WorkflowError naming the file, the step and the problem."""
    where = str(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise WorkflowError(f"{where}: cannot read: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise WorkflowError(f"{where}: not valid YAML: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("steps"), list) or not data["steps"]:
        raise WorkflowError(f"{where}: a workflow is a mapping with a non-empty list `steps`")
    unknown = set(data) - {"name", "description", "steps"}
    if unknown:
        raise WorkflowError(f"{where}: unknown key {sorted(unknown)[0]!r}; allowed: name, description, steps")
    steps: list[Step] = []
    for index, raw in enumerate(data["steps"], start=1):
        steps.append(_check_step(where, index, raw, steps, operations, args_model, config_model))
    return Workflow(name=str(data.get("name", path.stem)), path=path, text=text, steps=steps,
                    description=str(data.get("description", "")))


def _check_step(where: str, index: int, raw: Any, earlier: list[Step], operations: Operations,
                args_model: type[BaseModel] | None, config_model: type[BaseModel] | None) -> Step:
    if not isinstance(raw, dict):
        raise WorkflowError(f"{where}: step {index} is not a mapping")
    name = raw.get("name")
    label = f"{where}: step {index} ({name})" if name else f"{where}: step {index}"
    unknown = set(raw) - {"name", "op", "inputs", "params", "checkpoint"}
    if unknown:
        raise WorkflowError(f"{label}: unknown key {sorted(unknown)[0]!r}; allowed: name, op, inputs, params, "
                            f"checkpoint")
    if not isinstance(name, str) or not STEP_NAME.match(name):
        raise WorkflowError(f"{label}: name must be lower_case_words (a-z, 0-9, _), got {name!r}")
    if any(s.name == name for s in earlier):
        raise WorkflowError(f"{label}: a step named {name!r} already exists")
    op = operations.get(str(raw.get("op")))
    if op is None:
        close = _closest(str(raw.get("op")), list(operations.items))
        raise WorkflowError(f"{label}: unknown operation {raw.get('op')!r}{close}")
    inputs = raw.get("inputs") or {}
    if not isinstance(inputs, dict):
        raise WorkflowError(f"{label}: inputs must map input names to earlier steps")
    allowed_inputs = op.inputs + op.optional_inputs
    for key, source in inputs.items():
        if key not in allowed_inputs:
            raise WorkflowError(f"{label}: {op.name} has no input {key!r}; its inputs: "
                                f"{', '.join(allowed_inputs) or 'none'}")
        if not any(s.name == source for s in earlier):
            raise WorkflowError(f"{label}: input {key} uses {source!r}, which is not an earlier step")
    missing = [k for k in op.inputs if k not in inputs]
    if missing:
        raise WorkflowError(f"{label}: {op.name} needs input {missing[0]!r} (from an earlier step)")
    params = raw.get("params") or {}
    if not isinstance(params, dict):
        raise WorkflowError(f"{label}: params must be a mapping")
    for key, value in params.items():
        ref = _reference(value)
        if ref:
            model = args_model if ref[0] == "args" else config_model
            if model is None or ref[1] not in model.model_fields:
                known = ", ".join(model.model_fields) if model is not None else "none"
                raise WorkflowError(f"{label}: params.{key} refers to {value}, which does not exist "
                                    f"({ref[0]} has: {known})")
        elif isinstance(value, str) and ("$args" in value or "$config" in value or "${" in value):
            raise WorkflowError(f"{label}: params.{key} = {value!r}: a reference is the whole value, "
                                f"$args.NAME or $config.NAME")
    literal = {k: v for k, v in params.items() if _reference(v) is None}
    _validate_params(label, op, literal, partial=True)
    return Step(name=name, op=op.name, inputs=dict(inputs), params=dict(params),
                checkpoint=bool(raw.get("checkpoint", True)))


def _validate_params(label: str, op: Operation, values: dict[str, Any], partial: bool = False) -> BaseModel | None:
    try:
        return op.params.model_validate(values)
    except ValidationError as exc:
        errors = [e for e in exc.errors() if not (partial and e["type"] == "missing")]
        if errors:
            raise WorkflowError(describe_validation_error(
                ValidationError.from_exception_data(exc.title, errors), op.params, f"{label}: {op.name}",
                name_of=lambda loc: "params." + ".".join(str(p) for p in loc))) from None
    return None


def _closest(name: str, names: list[str]) -> str:
    import difflib
    close = difflib.get_close_matches(name, names, n=1)
    return f"; did you mean {close[0]}?" if close else f"; known: {', '.join(sorted(names))}"


def resolve_params(workflow: Workflow, operations: Operations, args: BaseModel | None,
                   config: BaseModel | None) -> dict[str, BaseModel]:
    """Every step's parameters with references filled in and validated: all before any step runs."""
    resolved: dict[str, BaseModel] = {}
    for index, step in enumerate(workflow.steps, start=1):
        values = {}
        for key, value in step.params.items():
            ref = _reference(value)
            if ref:
                value = getattr(args if ref[0] == "args" else config, ref[1])
            values[key] = value
        op = operations.items[step.op]
        params = _validate_params(f"{workflow.path}: step {index} ({step.name})", op, values)
        assert params is not None
        resolved[step.name] = params
    return resolved


# ---------------------------------------------------------------------------------------------
# Checkpoints: step results as JSON plus one .npz of their arrays (numpy scalars too, so they come
# back with their dtype)


def type_name(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def save_result(directory: Path, step: str, result: Any, types: Mapping[str, type] | None = None,
                seconds: float | None = None, compressed: bool = False) -> None:
    """`types`: the registered dataclasses (Operations.types); `seconds`: how long the step took,
    kept so that a resumed job still knows it; `compressed`: for results kept long (a product's
    views), not for checkpoints, which are written often and deleted."""
    arrays: dict[str, np.ndarray] = {}
    tree = _encode(result, arrays, types or {})
    if seconds is not None:
        tree = {"__result__": tree, "seconds": float(seconds)}
    directory.mkdir(parents=True, exist_ok=True)
    # The JSON goes first and comes back last: a step counts as done only when both halves are whole
    # and of the same save.
    (directory / f"{step}.json").unlink(missing_ok=True)
    save_npz_atomic(directory / f"{step}.npz", arrays, compressed)
    write_text_atomic(directory / f"{step}.json", json.dumps(tree))


def load_result(directory: Path, step: str, types: Mapping[str, type] | None = None) -> Any:
    return load_step(directory, step, types)[0]


def load_step(directory: Path, step: str, types: Mapping[str, type] | None = None) -> tuple[Any, float | None]:
    """A checkpointed result and the seconds its step took (None when not recorded)."""
    tree = json.loads((directory / f"{step}.json").read_text())
    seconds = None
    if isinstance(tree, dict) and "__result__" in tree:
        tree, seconds = tree["__result__"], tree.get("seconds")
    with np.load(directory / f"{step}.npz", allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    return _decode(tree, arrays, types or {}), seconds


def has_result(directory: Path, step: str) -> bool:
    return (directory / f"{step}.json").exists() and (directory / f"{step}.npz").exists()


def _encode(value: Any, arrays: dict[str, np.ndarray], types: Mapping[str, type]) -> Any:
    if isinstance(value, (np.ndarray, np.generic)):
        key = f"a{len(arrays)}"
        arrays[key] = np.asarray(value)
        return {"__array__" if isinstance(value, np.ndarray) else "__scalar__": key}
    if isinstance(value, GridSpec):
        return {"__grid__": value.to_json()}
    if isinstance(value, dict):
        return {"__dict__": [[k, _encode(v, arrays, types)] for k, v in value.items()]}
    if isinstance(value, (list, tuple)):
        return {"__tuple__" if isinstance(value, tuple) else "__list__": [_encode(v, arrays, types) for v in value]}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = [[f.name, _encode(getattr(value, f.name), arrays, types)] for f in dataclasses.fields(value)]
        name = type_name(type(value))
        return {"__object__": name, "__dict__": fields} if types.get(name) is type(value) else {"__dict__": fields}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"a step result cannot hold {type(value).__name__}")


def _decode(tree: Any, arrays: dict[str, np.ndarray], types: Mapping[str, type]) -> Any:
    if isinstance(tree, dict):
        if "__array__" in tree:
            return arrays[tree["__array__"]]
        if "__scalar__" in tree:
            return arrays[tree["__scalar__"]][()]
        if "__grid__" in tree:
            return GridSpec.from_json(tree["__grid__"])
        if "__object__" in tree:
            cls = types.get(tree["__object__"])
            if cls is None:
                raise WorkflowError(f"a checkpoint holds a {tree['__object__']}, which no operation names as a "
                                    "result type")
            return cls(**{k: _decode(v, arrays, types) for k, v in tree["__dict__"]})
        if "__dict__" in tree:
            return {k: _decode(v, arrays, types) for k, v in tree["__dict__"]}
        if "__list__" in tree:
            return [_decode(v, arrays, types) for v in tree["__list__"]]
        if "__tuple__" in tree:
            return tuple(_decode(v, arrays, types) for v in tree["__tuple__"])
    return tree


# ---------------------------------------------------------------------------------------------
# Running


@dataclass
class StepContext:
    """What an operation sees of the job: progress within its step, safe points, partial state."""

    job: JobContext                      # the JobContext
    step: str
    index: int
    total: int
    scratch: Path                 # a folder of its own, kept across break / continue
    params_all: Mapping[str, Any] = field(default_factory=dict)
    types: Mapping[str, type] = field(default_factory=dict)   # the operations' result types

    def progress(self, fraction: float, message: str) -> None:
        """Progress inside the step, 0..1; the job's percent counts whole steps."""
        fraction = min(max(fraction, 0.0), 1.0)
        self.job.progress(100.0 * (self.index - 1 + fraction) / self.total,
                          f"step {self.index}/{self.total} {self.step}: {message}")

    def safe_point(self) -> None:
        self.job.safe_point()

    def native(self, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """func(*args, **kwargs) in the native worker, named after this step (JobContext.native)."""
        return self.job.native(self.step, func, *args, **kwargs)

    def save_partial(self, key: str, result: Any) -> None:
        """A finished piece of a long step (one view of many), so continue does not redo it."""
        save_result(self.scratch, key, result, self.types)

    def load_partial(self, key: str) -> Any | None:
        return load_result(self.scratch, key, self.types) if has_result(self.scratch, key) else None


StepDone = Callable[[str, Any, float | None], None]   # on_step(name, result, seconds)


def run_workflow(workflow: Workflow, operations: Operations, params: dict[str, BaseModel], job: JobContext,
                 checkpoints: Path, on_step: StepDone | None = None) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Run the steps in order; finished steps found in `checkpoints` are loaded, not run again.

    on_step(name, result, seconds) is called as each step's result is there, run or loaded (seconds:
    how long it took when it ran, None if not known), so a command can write the parts of its product a
    step makes even when a later step fails, and write them again when a resumed job skips the step.

    Returns every step's result and the provenance of each step (op, parameters, seconds, whether
    it was resumed from a checkpoint)."""
    results: dict[str, Any] = {}
    provenance: list[dict[str, Any]] = []
    total = len(workflow.steps)
    for index, step in enumerate(workflow.steps, start=1):
        op = operations.items[step.op]
        record = {"step": step.name, "op": step.op, "params": params[step.name].model_dump(mode="json"),
                  "inputs": dict(step.inputs)}
        if step.checkpoint and has_result(checkpoints, step.name):
            results[step.name], took = load_step(checkpoints, step.name, operations.types)
            provenance.append({**record, "resumed": True})
            if on_step is not None:
                on_step(step.name, results[step.name], took)
            continue
        job.safe_point()
        job.progress(100.0 * (index - 1) / total, f"step {index}/{total} {step.name} ({step.op})")
        context = StepContext(job=job, step=step.name, index=index, total=total,
                              scratch=checkpoints / "partial" / step.name, types=operations.types)
        started = time.perf_counter()
        inputs = {key: results[source] for key, source in step.inputs.items()}
        result = op.func(context, params[step.name], **inputs)
        seconds = time.perf_counter() - started
        results[step.name] = result
        if step.checkpoint:
            save_result(checkpoints, step.name, result, operations.types, seconds)
            shutil.rmtree(context.scratch, ignore_errors=True)
        provenance.append({**record, "seconds": round(seconds, 4), "resumed": False})
        if on_step is not None:
            on_step(step.name, result, seconds)
    job.progress(100.0, f"workflow {workflow.name} done")
    return results, provenance


def describe_operations(operations: Operations) -> list[dict[str, Any]]:
    """For docs and `help`: every operation with its inputs and parameters."""
    out = []
    for name, op in sorted(operations.items.items()):
        out.append({"op": name, "summary": op.summary, "inputs": list(op.inputs),
                    "optional_inputs": list(op.optional_inputs),
                    "params": {k: str(v.annotation) for k, v in op.params.model_fields.items()}})
    return out
