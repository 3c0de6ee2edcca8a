"""``hil bench`` folder options given an empty path: refused while parsing, not dropped.

An empty ``--keep``/``--workdir`` used to be taken as no option at all: the bench ran in full
and threw its logs away in a temporary folder the user never asked for.
"""

from __future__ import annotations

import pytest

from rt_controller.cli import main


@pytest.mark.parametrize(
    "argv",
    [
        ["bench", "loop", "--rates", "50", "--duration", "0.1", "--host-probe", "0",
         "--lockstep-duration", "0", "--keep", ""],
        ["bench", "soak", "--duration", "3", "--sample", "1", "--warmup", "0", "--keep", ""],
        ["bench", "tuning", "--requests", "1", "--workdir", ""],
    ],
    ids=["loop-keep", "soak-keep", "tuning-workdir"],
)  # fmt: skip
def test_an_empty_folder_option_is_refused_before_the_bench_runs(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "-q"])
    assert exc.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert f"argument {argv[-2]}: the path is empty" in err


def test_bench_loop_refuses_a_kept_name_taken_by_a_folder_before_any_run(tmp_path, capsys):
    """A folder named like a later rate's log used to stop the bench after the earlier rates
    had run: their figures were lost. Now it is refused before the first run."""
    (tmp_path / "loop-200.mcap").mkdir()
    argv = ["bench", "loop", "--rates", "50,200", "--duration", "0.1", "--host-probe", "0"]
    assert main([*argv, "--lockstep-duration", "0", "--keep", str(tmp_path), "-q"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    (line,) = err.strip().splitlines()
    assert line.startswith("hil bench loop: error: --keep ")
    assert "loop-200.mcap" in line and "folder" in line
    assert not (tmp_path / "loop-50.mcap").exists()  # refused before the 50 Hz run
