"""``scripts/loaded_suite.py``: outcomes read from JUnit XML, flips across runs."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
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


def test_a_relative_out_is_the_callers_folder_and_holds_the_reports(tmp_path: Path) -> None:
    """pytest runs in the repository; ``--out runs`` given in another folder is that folder's
    ``runs``, where the script then reads the report (it read an empty folder and said 0)."""
    one = "tests/controller/test_loaded_suite_script.py::test_outcomes_of_every_kind"
    script = str(ROOT / "scripts/loaded_suite.py")
    argv = ["--runs", "1", "--hogs", "0", "--out", "runs", "--", one, "-p", "no:cacheprovider"]
    done = subprocess.run(
        [sys.executable, script, *argv], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "runs" / "run1.xml").exists()
    assert json.loads(done.stdout)["runs"][0]["passed"] == 1, done.stdout
