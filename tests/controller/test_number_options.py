"""Number options are refused one way: by their argparse type, while the subcommand's command
line is parsed (``hil SUB CMD: error: argument --X: ...``, status 2, NaN and inf included), and a
config-backed value names its key, plus the option when it came from the command line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hal.config import RigConfig
from rt_controller.config_rules import apply_overrides
from rt_controller.errors import ControllerConfigError
from tests.support import error_line


@pytest.fixture
def nothing_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bad option that reaches a bench or the monitor's zenoh session fails the test."""

    def started(*_: object, **__: object) -> None:
        raise AssertionError("a bad option was not refused before the work started")

    import hal.zenoh_session
    import rt_controller.rig.bench_loop
    import rt_controller.rig.bench_soak

    monkeypatch.setattr(rt_controller.rig.bench_loop, "bench_loop", started)
    monkeypatch.setattr(rt_controller.rig.bench_soak, "bench_soak", started)
    monkeypatch.setattr(hal.zenoh_session, "open_session", started)


CALIBRATE = ["camera", "calibrate", "--source", "emulated"]


@pytest.mark.parametrize(
    ("argv", "prefix"),
    [
        (["monitor", "--port", "65536"], "hil monitor: error: argument --port:"),
        (["monitor", "--port", "-1"], "hil monitor: error: argument --port:"),
        ([*CALIBRATE, "--views", "2"], "hil camera calibrate: error: argument --views:"),
        ([*CALIBRATE, "--views", "501"], "hil camera calibrate: error: argument --views:"),
        (["report", "x.mcap", "--max-list", "-1"], "hil report: error: argument --max-list:"),
        (["bench", "loop", "--host-probe", "nan"], "hil bench loop: error: argument --host-probe:"),
        (["bench", "loop", "--host-probe", "inf"], "hil bench loop: error: argument --host-probe:"),
        (["bench", "loop", "--host-probe", "601"], "hil bench loop: error: argument --host-probe:"),
        (["bench", "loop", "--rates", "50,nan"], "hil bench loop: error: argument --rates:"),
        (["bench", "loop", "--rates", "inf"], "hil bench loop: error: argument --rates:"),
        (["bench", "loop", "--rates", "50,5000"], "hil bench loop: error: argument --rates:"),
        (["bench", "loop", "--rates", ","], "hil bench loop: error: argument --rates:"),
        (["bench", "soak", "--warmup", "nan"], "hil bench soak: error: argument --warmup:"),
        (["bench", "soak", "--warmup", "-1"], "hil bench soak: error: argument --warmup:"),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else None,
)
def test_a_number_option_is_refused_by_its_subcommand_parser(
    argv: list[str], prefix: str, capsys: pytest.CaptureFixture[str], nothing_starts: None
) -> None:
    assert error_line(argv, capsys).startswith(prefix)


def test_a_warmup_not_below_the_duration_is_refused(
    capsys: pytest.CaptureFixture[str], nothing_starts: None
) -> None:
    err = error_line(["bench", "soak", "--duration", "5", "--warmup", "5"], capsys)
    assert "--warmup must be less than --duration (5 s), got 5" in err


@pytest.mark.parametrize("value", ["0", "-3", "nan", "inf"])
def test_a_bad_rate_names_the_key_and_the_option(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = error_line(["simulate", "--rate", value], capsys)
    assert f"rates.control_hz (--rate): must be a positive number, got {float(value)!r}" in err


def test_an_option_checked_by_the_config_names_the_key_and_the_option(
    capsys: pytest.CaptureFixture[str],
) -> None:
    err = error_line(["simulate", "--horizon", "20"], capsys)
    assert "rhc.horizon (--horizon): 20.0 is out of range (0, 10]" in err


@pytest.mark.parametrize("rate", [0.0, math.nan, math.inf, "x"])
def test_apply_overrides_names_only_the_key_outside_the_command_line(rate: object) -> None:
    with pytest.raises(ControllerConfigError) as exc:
        apply_overrides(RigConfig(), rate=rate)  # type: ignore[arg-type]
    assert str(exc.value) == f"rates.control_hz: must be a positive number, got {rate!r}"


@pytest.mark.parametrize(
    ("key", "value", "said"),
    [
        ("rates.control_hz", "0.0", "(rates.control_hz = 0.0): must be a positive number, got 0.0"),
        ("rates.control_hz", '"x"', "(rates.control_hz = 'x'): must be a positive number, got 'x'"),
        ("rhc.horizon", '"x"', "(rhc.horizon = 'x'): expected a number, got 'x'"),
    ],
)
def test_a_sweep_axis_value_is_refused_by_its_key(
    key: str, value: str, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("dask")
    spec = tmp_path / "spec.toml"
    spec.write_text(
        f'[study]\nduration_s = 0.2\nrepetitions = 1\n[[axes]]\nkey = "{key}"\n'
        f"values = [{value}, 50]\n"
    )
    argv = ["sweep", str(spec), "--no-progress", "--out", str(tmp_path / "out")]
    err = error_line(argv, capsys)
    assert said in err and "--rate" not in err and err.count(key) == 1, err
