"""``hil bench loop --rates``: two rates that name the same log file are one rate twice."""

from __future__ import annotations

import pytest

from rt_controller.cli import main


def test_rates_that_print_alike_are_refused_as_given_twice(capsys):
    """50 and 50.0000001 Hz both write loop-50.mcap: the second run would replace the first's
    log, and the first's record would name the second's."""
    with pytest.raises(SystemExit) as exc:
        main(["bench", "loop", "--rates", "50,50.0000001", "-q"])
    assert exc.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert "given twice" in err.strip().splitlines()[-1]
