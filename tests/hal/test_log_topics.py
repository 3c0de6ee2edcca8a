"""The MCAP and live topic names are spelled once, in ``hal/log_topics.py``: no other product
module writes one of them as a string literal (a second spelling drifts from the first)."""

from __future__ import annotations

import ast
from pathlib import Path

import hal.log_topics as log_topics

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("hal", "vision", "plant_emulator", "rt_controller")
TABLE = ROOT / "hal" / "log_topics.py"


def topic_names() -> set[str]:
    return {v for k, v in vars(log_topics).items() if k.endswith("_TOPIC")}


def spelled_topics(path: Path, names: set[str]) -> set[str]:
    """The topic names that ``path`` writes as string literals."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    return {
        node.value
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
    }


def test_the_table_names_every_topic_once():
    names = [v for k, v in vars(log_topics).items() if k.endswith("_TOPIC")]
    assert len(names) == len(set(names)) >= 17
    assert all(n.startswith("/") for n in names)


def test_no_module_but_the_table_spells_a_topic():
    names = topic_names()
    offenders = {
        path.relative_to(ROOT).as_posix(): sorted(found)
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
        if path != TABLE and (found := spelled_topics(path, names))
    }
    assert not offenders, offenders


def test_the_checker_sees_a_spelled_topic(tmp_path: Path):
    probe = tmp_path / "probe.py"
    probe.write_text('TOPIC = "/camera/image"\nOTHER = "/camera/image/not"\n')
    assert spelled_topics(probe, topic_names()) == {"/camera/image"}
