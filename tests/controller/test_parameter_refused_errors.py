"""A refused parameter change is in the controller's exception tree (``cli.main`` turns a
:class:`ControllerError` into one line and exit 2, never a traceback) and still a
``ValueError`` for the callers that catch it so."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import ParameterRefused, judge
from rt_controller.errors import ControllerConfigError, ControllerError


@pytest.mark.parametrize(
    "changes", [{}, {"rates.control_hz": 100.0}, {"gains.kp": -1.0}], ids=["none", "key", "value"]
)
def test_a_refused_change_is_a_controller_error(changes: dict[str, float]) -> None:
    with pytest.raises(ControllerError) as caught:
        judge(RigConfig(), changes)
    assert type(caught.value) is ParameterRefused
    assert isinstance(caught.value, ControllerConfigError) and isinstance(caught.value, ValueError)
