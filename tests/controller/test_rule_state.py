"""The compiled rule's state is declared once (``rt_controller/control/state.py``): the
offsets, the work vector's cut, the Decision's fields, the cycle record's decision part and its
JSON Schema all follow from it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hal.config import RigConfig
from rt_controller.control import state
from rt_controller.control.controller import Controller
from rt_controller.control.model import NominalModel
from rt_controller.control.rhc.problem import pack_params
from rt_controller.runtime import cycle_record

BLOCKS = (state.IO, state.LIM, state.KS, state.PAR, state.IP, state.ST, state.W, state.CUT)
BLOCKS += (state.XS, state.STAGE, state.AUX, state.PRE, state.VEC, state.SMALL)


@pytest.mark.parametrize("block", BLOCKS, ids=lambda b: b.__name__.rsplit(".", 1)[1])
def test_a_block_lays_its_fields_end_to_end(block):
    off = 0
    for f in block.fields:
        assert block.offset(f.name) == off, f.name
        off += f.size
    assert off == block.SIZE


def test_the_io_vector_holds_the_inputs_then_the_outputs():
    assert sum(f.size for f in state.INPUTS) == state.IO.OUTPUTS
    assert state.IO.offset(state.OUTPUTS[0].name) == state.IO.OUTPUTS


def test_the_checked_in_schema_holds_the_declared_decision():
    """``python -m rt_controller.runtime.cycle_record`` regenerates it after a change."""
    schema = json.loads(cycle_record.SCHEMA_FILE.read_text(encoding="utf-8"))
    assert schema == cycle_record.schema_with_decision(schema)
    props = list(schema["properties"])
    decision = list(cycle_record.decision_schema())
    start = props.index(decision[0])
    assert props[start : start + len(decision)] == decision


@pytest.mark.parametrize("law", ["ioc", "rhc"])
def test_a_decision_records_the_declared_fields_with_their_types(law):
    cfg = RigConfig().with_overrides({"controller.law": law})
    ctl = Controller(cfg)
    q, dq, f = (np.array(v, float) for v in (cfg.scenario.q0, cfg.scenario.dq0, cfg.scenario.f0))
    d = ctl.decide(0.0, q, dq, f, f_stale=False, state_stale=False)
    rec = d.record_fields(ctl.law)
    schema = cycle_record.decision_schema()
    assert list(rec) == list(schema)
    python_type = {"number": float, "integer": int, "boolean": bool, "string": str}
    for name, prop in schema.items():
        if prop["type"] == "array":
            assert len(rec[name]) == 2 and all(isinstance(x, float) for x in rec[name])
        else:
            assert isinstance(rec[name], python_type[prop["type"]]), name
    assert rec["law"] == law and d.mode == "control"
    for f in state.OUTPUTS:  # every output is the Decision's attribute by its declared name
        value = getattr(d, f.name)
        k = state.IO.offset(f.name)
        want = rec.get(f.name, None)
        if f.record == "vector":
            assert np.array_equal(value, want)
        elif f.record in ("number",):
            assert value == want
        assert np.shape(value) == (() if f.size == 1 else (f.size,)), (f.name, k)


def test_the_work_cut_tiles_the_work_vector():
    cfg = RigConfig()
    _, iP = pack_params(NominalModel.from_config(cfg), cfg)
    cut = iP[state.IP.WORK : state.IP.WORK + state.IP.field("work").size]
    cut = cut.reshape(-1, state.CUT.SIZE)
    end = 0
    for (off, rows, cols), a in zip(cut, state.WORK, strict=True):
        assert off == end, a.name
        end = off + rows * cols
    n, s, m = cfg.rhc.steps, iP[state.IP.SUB], max(iP[state.IP.KMAX], iP[state.IP.INIT_KRYLOV])
    assert state.work_offsets(n, s, m)[1] == end == state.work_length(iP)


def test_an_output_the_rule_left_nan_is_recorded_as_null_whatever_its_type() -> None:
    """NaN is "not acted on" for every record type: a boolean left NaN is null, not ``true``
    (NaN != 0), and an integer is null, not a ValueError from ``int(nan)``."""
    from rt_controller.control.controller import Decision

    io = np.full(state.IO.SIZE, np.nan)
    io[state.IO.MODE] = 0.0
    fields = Decision(io, "disarmed", 0).record_fields("ioc")
    kinds = {f.name: f.record for f in state.OUTPUTS if f.record in ("boolean", "integer")}
    assert set(kinds.values()) == {"boolean", "integer"}
    assert all(fields[name] is None for name in kinds), fields
