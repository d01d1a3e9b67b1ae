"""The workflow engine: checking files before anything runs, references, checkpoints and resume."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from rvs_server.config import CommandConfig, Settings
from rvs_server.workflow import (
    Operations,
    StepParams,
    WorkflowError,
    load_result,
    load_step,
    load_workflow,
    resolve_params,
    run_workflow,
    save_result,
)
from toolbox.grid import GridSpec

ops = Operations()
calls: list[str] = []


class MakeParams(StepParams):
    count: int = Field(..., ge=1, le=1000)
    value: float = 1.0


class ScaleParams(StepParams):
    factor: float = Field(2.0, gt=0)


@ops.register("toy.make", MakeParams)
def make(step, params):
    calls.append("make")
    pieces = []
    for i in range(params.count):  # a long step with resumable pieces
        piece = step.load_partial(f"piece{i}")
        if piece is None:
            step.safe_point()
            calls.append(f"piece{i}")
            piece = np.full(3, params.value + i)
            step.save_partial(f"piece{i}", piece)
        pieces.append(piece)
    return {"values": np.concatenate(pieces), "grid": GridSpec(0.0, 0.0, 0.5, 2, 3)}


@ops.register("toy.scale", ScaleParams, inputs=("data",))
def scale(step, params, data):
    calls.append("scale")
    return {"values": data["values"] * params.factor, "grid": data["grid"]}


class Args(CommandConfig):
    count: int = 3
    factor: float = 3.0


class Conf(Settings):
    base: float = 10.0


GOOD = """
name: toy
steps:
  - name: make
    op: toy.make
    params: {count: $args.count, value: $config.base}
  - name: scaled
    op: toy.scale
    inputs: {data: make}
    params:
      factor: ${args.factor}
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "flow.yaml"
    path.write_text(text)
    return path


def test_a_good_workflow_runs_and_records_provenance(tmp_path):
    flow = load_workflow(write(tmp_path, GOOD), ops, Args, Conf)
    params = resolve_params(flow, ops, Args(), Conf())

    class Job:
        def progress(self, *a): pass
        def safe_point(self): pass
    results, provenance = run_workflow(flow, ops, params, Job(), tmp_path / "ckpt")
    assert np.array_equal(results["scaled"]["values"], np.repeat([10.0, 11.0, 12.0], 3) * 3)
    assert [p["step"] for p in provenance] == ["make", "scaled"]
    assert provenance[0]["params"] == {"count": 3, "value": 10.0}


@pytest.mark.parametrize("text, words", [
    (GOOD.replace("toy.scale", "toy.scael"),
     ["step 2 (scaled)", "unknown operation 'toy.scael'", "did you mean toy.scale"]),
    (GOOD.replace("{data: make}", "{data: later}"),
     ["step 2 (scaled)", "input data uses 'later'", "not an earlier step"]),
    (GOOD.replace("    inputs: {data: make}\n", ""), ["step 2 (scaled)", "needs input 'data'"]),
    (GOOD.replace("{data: make}", "{data: make, extra: make}"), ["has no input 'extra'"]),
    (GOOD.replace("factor: ${args.factor}", "factor: -1"), ["step 2 (scaled)", "params.factor", "-1", "> 0"]),
    (GOOD.replace("factor: ${args.factor}", "fator: 2"), ["params.fator", "unknown field"]),
    (GOOD.replace("${args.factor}", "${args.nope}"), ["refers to ${args.nope}", "does not exist"]),
    (GOOD.replace("name: scaled", "name: make"), ["already exists"]),
    ("steps: []", ["non-empty list"]),
    ("steps: [\n", ["not valid YAML"]),
])
def test_broken_files_are_refused_naming_file_step_and_reason(tmp_path, text, words):
    with pytest.raises(WorkflowError) as info:
        load_workflow(write(tmp_path, text), ops, Args, Conf)
    assert "flow.yaml" in str(info.value)
    for word in words:
        assert word in str(info.value)


def test_a_bad_value_from_the_command_is_refused_before_any_step_runs(tmp_path):
    flow = load_workflow(write(tmp_path, GOOD), ops, Args, Conf)
    with pytest.raises(WorkflowError, match="params.count"):
        resolve_params(flow, ops, Args(count=0), Conf())


def test_an_interrupted_run_resumes_at_the_running_step_and_piece(tmp_path):
    flow = load_workflow(write(tmp_path, GOOD), ops, Args, Conf)
    params = resolve_params(flow, ops, Args(count=4), Conf())

    class Stop(Exception):
        pass

    class Job:
        def __init__(self, stop_after: int | None):
            self.points = 0
            self.stop_after = stop_after
        def progress(self, *a): pass
        def safe_point(self):
            self.points += 1
            if self.stop_after is not None and self.points > self.stop_after:
                raise Stop()

    calls.clear()
    with pytest.raises(Stop):
        run_workflow(flow, ops, params, Job(stop_after=3), tmp_path / "ckpt")
    assert calls == ["make", "piece0", "piece1"]
    calls.clear()
    results, provenance = run_workflow(flow, ops, params, Job(None), tmp_path / "ckpt")
    assert calls == ["make", "piece2", "piece3", "scale"]  # pieces 0 and 1 were not made again
    calls.clear()
    again, provenance = run_workflow(flow, ops, params, Job(None), tmp_path / "ckpt")
    assert calls == [] and all(p["resumed"] for p in provenance)
    assert np.array_equal(again["scaled"]["values"], results["scaled"]["values"])


def test_results_round_trip_through_checkpoints(tmp_path):
    value = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "grid": GridSpec(1.0, -2.0, 0.1, 4, 5),
             "list": [1, "x", None, np.int64(3)], "nested": {"b": np.array([True, False])}}
    save_result(tmp_path, "s", value)
    back = load_result(tmp_path, "s")
    assert back["grid"] == value["grid"] and back["list"] == [1, "x", None, 3]
    assert np.array_equal(back["a"], value["a"]) and back["a"].dtype == np.float32


@dataclass(frozen=True)
class Fit:
    scale: np.float64
    axes: tuple[float, float] | None
    inner: Inner
    notes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Inner:
    points: np.ndarray
    count: int


@dataclass(frozen=True)
class Unnamed:
    value: float


def test_results_holding_dataclasses_come_back_as_themselves(tmp_path):
    """A step whose result is not arrays (hop-plan's reconstruction, estimate, plan): the dataclasses its
    operations name come back as themselves, numpy scalars with their dtype and tuples as tuples, so a
    resumed step hands on what a run one would; a dataclass not named comes back as a dict, as before."""
    types = Operations()
    types.result_types(Fit, Inner)
    value = {"fit": Fit(np.float64(0.25), (1.0, 2.0), Inner(np.arange(3.0), 3), {"ok": np.bool_(True)}),
             "cell": (2, 3), "other": Unnamed(1.5), "none": None}
    save_result(tmp_path, "s", value, types.types, seconds=1.25)
    back, seconds = load_step(tmp_path, "s", types.types)
    fit = back["fit"]
    assert isinstance(fit, Fit) and isinstance(fit.inner, Inner) and seconds == 1.25
    assert type(fit.scale) is np.float64 and fit.scale == 0.25 and fit.axes == (1.0, 2.0)
    assert np.array_equal(fit.inner.points, value["fit"].inner.points) and fit.inner.count == 3
    assert type(fit.notes["ok"]) is np.bool_ and back["cell"] == (2, 3) and back["none"] is None
    assert back["other"] == {"value": 1.5}
    with pytest.raises(WorkflowError, match="no operation names"):
        load_result(tmp_path, "s")
    with pytest.raises(TypeError, match="not a dataclass"):
        types.result_types(dict)
    save_result(tmp_path, "plain", {"a": 1})   # saved without seconds, as partial results are
    assert load_step(tmp_path, "plain") == ({"a": 1}, None)


def test_on_step_sees_each_result_as_it_is_made_or_loaded_with_its_seconds(tmp_path):
    flow = load_workflow(write(tmp_path, GOOD), ops, Args, Conf)
    params = resolve_params(flow, ops, Args(count=2), Conf())

    class Job:
        def progress(self, *a): pass
        def safe_point(self): pass
    seen: list[tuple[str, float | None]] = []
    first, _ = run_workflow(flow, ops, params, Job(), tmp_path / "ckpt", on_step=lambda n, r, s: seen.append((n, s)))
    assert [name for name, _ in seen] == ["make", "scaled"] and all(s is not None and s >= 0 for _, s in seen)
    again: list[tuple[str, object, float | None]] = []
    run_workflow(flow, ops, params, Job(), tmp_path / "ckpt", on_step=lambda n, r, s: again.append((n, r, s)))
    assert [(name, s) for name, _, s in again] == seen   # loaded, with the seconds the run took
    assert np.array_equal(again[1][1]["values"], first["scaled"]["values"])
