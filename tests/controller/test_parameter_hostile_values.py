"""A change set a key holder can send that the TOML rules never meet (a JSON integer too large
for a float, a huge value echoed in the reason) is refused in one short line and counted; it
never raises into the control thread, which would end the run with a traceback."""

from __future__ import annotations

import pytest

from hal.config import RigConfig
from rt_controller.calibration.parameters import ParameterService, Request

HUGE = 10**400  # what `hil param set 'rhc.zeta=1000...0'` sends: JSON has no integer limit


@pytest.mark.parametrize(
    "changes",
    [
        {"rhc.zeta": HUGE},
        {"gains.kp": -HUGE},
        {"gains.alpha": [[HUGE, 0], [0, 1]]},
        {"rhc.u_max": [HUGE, 1]},
        {"gains.kp": 0.2, "gains.K": [HUGE, 1.0]},
    ],
    ids=["scalar", "negative", "matrix", "list", "with-a-good-key"],
)
def test_a_huge_integer_is_refused_and_counted(changes: dict) -> None:
    service = ParameterService(RigConfig())
    answers = []
    service.submit(Request(changes, source="test", reply=answers.append))
    cfg, outcomes = service.due(5)
    assert cfg is None and service.param_set == 0
    assert service.cfg.gains.kp == RigConfig().gains.kp
    (out,) = outcomes
    assert answers == [out] and not out.accepted and out.tick == 5
    key = next(k for k, v in changes.items() if "0000000000" in repr(v))
    assert key in out.reason and "\n" not in out.reason
    assert service.counters.as_dict() == {"accepted": 0, "refused": 1, "unauthenticated": 0}


def test_the_reason_stays_one_short_line_for_a_huge_value() -> None:
    service = ParameterService(RigConfig())
    service.submit(Request({"rhc.kmax": "x" * 1_000_000, "rhc.zeta": "a\nb"}, source="test"))
    _, (out,) = service.due(0)
    assert not out.accepted and out.reason.startswith("rhc.")
    assert len(out.reason) <= 400 and "\n" not in out.reason
