"""``hil camera calibrate`` off the happy path: a read-only rig config, a config's file mode,
options of the emulated views given with a folder of images, a folder copied from a Mac (its
``._*`` AppleDouble files beside the views)."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from rt_controller.cli import main


def calibrate(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict, str]:
    status = main(["camera", "calibrate", *args, "--json"])
    captured = capsys.readouterr()
    return status, json.loads(captured.out) if captured.out.strip() else {}, captured.err


@pytest.fixture(scope="module")
def views(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Eight emulated views saved as PNG, as a real camera's folder."""
    folder = tmp_path_factory.mktemp("views")
    argv = ["camera", "calibrate", "--source", "emulated", "--views", "8"]
    assert main([*argv, "--save-views", str(folder), "--json"]) == 0
    return folder


def test_a_read_only_config_is_not_replaced(tmp_path: Path, views: Path, capsys):
    """chmod a-w rig.toml says "do not touch": it was replaced by a rename and made 0644."""
    rig = tmp_path / "rig.toml"
    rig.write_text("# my rig\n")
    rig.chmod(0o444)
    status, out, err = calibrate(capsys, "--images", str(views), "--config", str(rig))
    assert status == 2 and out == {}, err
    assert err.strip() == (
        f"hil camera calibrate: error: {rig}: read-only, not touched (make it writable, or "
        "give --write FILE)"
    )
    assert rig.read_text() == "# my rig\n" and stat.S_IMODE(rig.stat().st_mode) == 0o444


def test_writing_the_config_keeps_its_file_mode(tmp_path: Path, views: Path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text("# my rig\n")
    rig.chmod(0o640)
    status, out, _ = calibrate(capsys, "--images", str(views), "--write", str(rig))
    assert status == 0 and out["written"] == str(rig)
    assert "calibrated = true" in rig.read_text()
    assert stat.S_IMODE(rig.stat().st_mode) == 0o640


@pytest.mark.parametrize(
    "option", [("--views", "12"), ("--seed", "3"), ("--save-views", "{tmp}/saved")], ids=str
)
def test_options_of_the_emulated_views_are_refused_with_images(
    tmp_path: Path, views: Path, capsys, option: tuple[str, str]
):
    """They did nothing with --images, silently (the folder's views are what they are)."""
    given = (option[0], option[1].format(tmp=tmp_path))
    status, out, err = calibrate(capsys, "--images", str(views), *given)
    assert status == 2 and out == {}
    assert err.strip() == (
        f"hil camera calibrate: error: {option[0]}: only with --source emulated (--images "
        "calibrates from the folder's views as they are)"
    )
    assert not (tmp_path / "saved").exists()


def test_hidden_files_beside_the_views_are_not_views(tmp_path: Path, views: Path, capsys):
    """A folder copied from a Mac holds ``._view-000.png`` (AppleDouble metadata, no image)."""
    folder = tmp_path / "views"
    folder.mkdir()
    for p in sorted(views.glob("*.png")):
        (folder / p.name).write_bytes(p.read_bytes())
        (folder / f"._{p.name}").write_bytes(b"\0\5\26\7" + b"\0" * 60)
    status, out, err = calibrate(capsys, "--images", str(folder))
    assert status == 0, err
    assert out["views_total"] == 8 and out["views_used"] == 8


def test_saving_views_into_a_folder_of_earlier_views_is_refused(tmp_path: Path, capsys):
    """Eight views saved, then four more over them at another seed: the folder held four of
    each run, and ``--images`` on it calibrated from both (another lens, another pose set)."""
    folder = tmp_path / "views"
    argv = ["--source", "emulated", "--views", "8", "--save-views", str(folder)]
    assert calibrate(capsys, *argv)[0] == 0
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    status, out, err = calibrate(
        capsys, "--source", "emulated", "--views", "4", "--seed", "1", "--save-views", str(folder)
    )
    assert status == 2 and out == {}, err
    assert err.strip() == (
        f"hil camera calibrate: error: --save-views {folder}: already holds 8 saved views "
        "(view-*.png): give an empty or new folder"
    )
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
