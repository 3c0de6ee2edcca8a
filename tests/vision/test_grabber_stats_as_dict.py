"""The grabber's stats become a dict through ``as_dict()`` (``hil vision --json``): every field
by name, in order, JSON-ready."""

from __future__ import annotations

import dataclasses
import json

from vision.grabber import GrabberStats


def test_the_stats_dict_is_every_field_in_order() -> None:
    stats = GrabberStats(source="emulated", frames=3, pipeline={"rejected": {"malformed": 1}})
    d = stats.as_dict()
    assert list(d) == [f.name for f in dataclasses.fields(GrabberStats)]
    assert d["frames"] == 3 and d["pipeline"] == {"rejected": {"malformed": 1}}
    assert json.loads(json.dumps(d)) == d
