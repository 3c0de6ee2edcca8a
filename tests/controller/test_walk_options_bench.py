"""``hil bench`` options off the happy path: ``tuning --workdir`` says in its help that it
replaces the files of an earlier bench (as ``loop --keep`` and ``soak --keep`` do)."""

from __future__ import annotations

import pytest

from rt_controller.cli import main


def help_text(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--help"])
    assert exc.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_tuning_workdir_help_says_it_replaces_the_files_there(
    capsys: pytest.CaptureFixture[str],
) -> None:
    text = help_text(["bench", "tuning"], capsys)
    assert "tuning.mcap" in text and "bench.key" in text
    assert "replacing an earlier bench's" in text


def test_loop_says_the_monitor_port_it_chose_for_port_0(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import rt_controller.rig.bench_loop

    seen: dict[str, object] = {}

    def bench_loop(*_: object, **kwargs: object) -> dict:
        seen.update(kwargs)  # the rig's runs are not what this test is about
        return {"rates": [], "monitor_port": kwargs["monitor_port"]}

    monkeypatch.setattr(rt_controller.rig.bench_loop, "bench_loop", bench_loop)
    code = main(["bench", "loop", "--monitor-port", "0", "--host-probe", "0", "-q"])
    captured = capsys.readouterr()
    port = seen["monitor_port"]
    assert code == 0 and isinstance(port, int) and 0 < port < 65536
    assert f"ws://127.0.0.1:{port}" in captured.err
    assert f'"monitor_port": {port}' in captured.out
