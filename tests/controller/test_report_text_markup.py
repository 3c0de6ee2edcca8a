"""hil report's text is printed with rich: a log path, an operator's note or a parameter change
holding square brackets is shown as written, not read as rich markup (which dropped "[red]"
and raised a traceback on a closing tag like "[/y]")."""

from __future__ import annotations

from hal.config import RigConfig
from rt_controller.cli import main
from rt_controller.runtime.recorder import CycleRecorder


def _log(path, *, note: str = ""):
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = CycleRecorder(path, RigConfig())
    for k in range(5):
        rec.record_cycle(
            {"tick": k, "t_ns": 10**9 + k * 20_000_000, "sim_time_s": k * 0.02, "cycle_us": 1e2}
        )
    if note:
        rec.record_event(
            {
                "tick": 2,
                "t_ns": 10**9 + 40_000_000,
                "action": "mark",
                "accepted": True,
                "note": note,
                "source": "op[/1]",
            }
        )
    rec.close()
    return path


def test_a_log_path_with_brackets_is_printed_as_it_is(tmp_path, capsys):
    log = _log(tmp_path / "x[" / "y]" / "[red]run.mcap")  # "x[/y]": a closing tag in markup
    figs = tmp_path / "figs[/z]"
    assert main(["report", "-q", "--plot", str(figs), str(log)]) == 0
    out = capsys.readouterr().out.replace("\n", "")
    assert str(log) in out
    assert str(figs) in out


def test_an_operator_note_with_brackets_is_printed_as_it_is(tmp_path, capsys):
    log = _log(tmp_path / "run.mcap", note="[/b] gain [x2] step")
    assert main(["report", "-q", str(log)]) == 0
    out = capsys.readouterr().out
    assert "[/b] gain [x2] step" in out
    assert "op[/1]" in out
