"""The workflow engine: checking files before anything runs, references, checkpoints and resume."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from rvs_server.config import CommandConfig, Settings
from toolbox.grid import GridSpec
from rvs_server.workflow import (Operations, StepParams, WorkflowError, load_result, load_workflow,
                                 resolve_params, run_workflow, save_result)

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
    (GOOD.replace("toy.scale", "toy.scael"), ["step 2 (scaled)", "unknown operation 'toy.scael'", "did you mean toy.scale"]),
    (GOOD.replace("{data: make}", "{data: later}"), ["step 2 (scaled)", "input data uses 'later'", "not an earlier step"]),
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
