"""Every ``--json`` line is strict JSON: what Python would write as ``NaN`` or ``Infinity``
(which ``jq`` and JavaScript refuse) is ``null``."""

from __future__ import annotations

import json
import math

import pytest

from hal.strict_json import dumps, finite


def strict_loads(text: str):
    def refuse(name: str):
        raise ValueError(f"not strict JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_floats_are_null_at_any_depth():
    obj = {"J": math.nan, "f": [math.inf, 1.5], "t": (-math.inf, 2), "n": {"x": [math.nan]}}
    assert strict_loads(dumps(obj)) == {
        "J": None,
        "f": [None, 1.5],
        "t": [None, 2],
        "n": {"x": [None]},
    }
    assert finite({"ok": 1.0, "s": "NaN"}) == {"ok": 1.0, "s": "NaN"}


def test_a_summary_of_a_run_that_never_ran_the_law_prints_strict_json(capsys):
    """``hil controller --json`` stopped before arming: f_final and f_final_norm were NaN."""
    from rt_controller.commands.output import print_summary

    summary = {"ticks": 0, "f_final": [math.nan, math.nan], "f_final_norm": math.nan}
    print_summary(summary, True, "hil controller")
    out = capsys.readouterr().out
    assert strict_loads(out) == {"ticks": 0, "f_final": [None, None], "f_final_norm": None}


def test_what_cannot_be_json_still_fails_loudly():
    with pytest.raises(TypeError):
        dumps({"x": object()})


def test_numpy_values_become_plain_numbers_and_null():
    import numpy as np

    obj = {"a": np.array([1.0, np.nan]), "b": np.float64(np.inf), "c": np.int32(3)}
    assert strict_loads(dumps(obj)) == {"a": [1.0, None], "b": None, "c": 3}
