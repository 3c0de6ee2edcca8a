"""A sweep's results folder damaged between runs (a journal with bytes that are no text, a
sweep.json that is JSON but no object): a resume says so in one line or runs the unreadable
rows again, never a traceback."""

from __future__ import annotations

import json

import pytest

from rt_controller.errors import ControllerConfigError
from rt_controller.sweep.results import ResultStore
from rt_controller.sweep.spec import spec_from_dict

AXIS = {"key": "plant.z_wo", "values": [0.9, 1.1]}


@pytest.mark.parametrize("meta", ["[1, 2]", '"done"', "3"])
def test_a_sweep_json_that_is_no_object_is_refused_in_one_line(tmp_path, meta):
    (tmp_path / "sweep.json").write_text(meta)
    with pytest.raises(ControllerConfigError, match=r"unreadable sweep\.json: not a JSON object"):
        ResultStore(tmp_path, spec_from_dict({"axes": [AXIS]}))
    assert (tmp_path / "sweep.json").read_text() == meta


def test_a_journal_line_that_is_no_text_is_run_again_and_the_others_kept(tmp_path):
    spec = spec_from_dict({"axes": [AXIS]})
    row = {"run_key": "k1", "engine": "simulate", "status": "ok", "point": 0, "rep": 0}
    (tmp_path / "sweep.json").write_text(json.dumps({"spec_hash": spec.spec_hash}))
    (tmp_path / "rows.jsonl").write_bytes(b"\xff\xfe{torn\n" + json.dumps(row).encode() + b"\n")
    with ResultStore(tmp_path, spec) as store:
        assert store.done() == {"k1"}
