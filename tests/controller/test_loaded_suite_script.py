"""``scripts/loaded_suite.py``: outcomes read from JUnit XML, flips across runs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

JUNIT = """<?xml version="1.0" encoding="utf-8"?>
<testsuites><testsuite name="pytest">
<testcase classname="tests.a" name="test_ok" time="0.1"/>
<testcase classname="tests.a" name="test_bad" time="0.1"><failure message="x">x</failure></testcase>
<testcase classname="tests.a" name="test_err" time="0.1"><error message="e">e</error></testcase>
<testcase classname="tests.a" name="test_skip" time="0"><skipped type="pytest.skip" message="s"/>
</testcase>
<testcase classname="tests.a" name="test_xf" time="0"><skipped type="pytest.xfail" message="r"/>
</testcase>
</testsuite></testsuites>
"""


def _script():
    spec = importlib.util.spec_from_file_location("loaded_suite", ROOT / "scripts/loaded_suite.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_outcomes_of_every_kind(tmp_path: Path) -> None:
    path = tmp_path / "run.xml"
    path.write_text(JUNIT)
    assert _script().outcomes(path) == {
        "tests.a::test_ok": "passed",
        "tests.a::test_bad": "failed",
        "tests.a::test_err": "error",
        "tests.a::test_skip": "skipped",
        "tests.a::test_xf": "xfailed",
    }


def test_flips_lists_only_tests_whose_outcome_differs() -> None:
    runs = [
        {"t1": "passed", "t2": "passed", "t3": "failed"},
        {"t1": "passed", "t2": "failed", "t3": "failed"},
        {"t1": "passed", "t2": "passed"},
    ]
    assert _script().flips(runs) == {
        "t2": ["passed", "failed", "passed"],
        "t3": ["failed", "failed", None],
    }
    assert _script().flips([runs[0], runs[0], runs[0]]) == {}
