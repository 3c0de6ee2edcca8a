"""``hil export`` reads and checks the log before it makes any output folder: a log it
refuses (not an MCAP file, no such file) leaves no new ``--out`` folder behind."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

HIL = str(Path(sys.executable).parent / "hil")


def hil(*argv: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [HIL, *map(str, argv)], capture_output=True, text=True, timeout=300, check=False
    )


@pytest.mark.parametrize("content", [b"garbage, not a log", b"", None])
@pytest.mark.parametrize(
    ("fmt", "out"),
    [("csv", "new/deeper"), ("parquet", "new/run.cycle.parquet"), ("mat", "new/run.mat")],
)
def test_a_refused_log_makes_no_output_folder(
    tmp_path: Path, content: bytes | None, fmt: str, out: str
) -> None:
    log = tmp_path / "run.mcap"
    if content is not None:
        log.write_bytes(content)
    topics = ["--topics", "cycle"] if fmt == "parquet" else []
    done = hil("export", log, "--format", fmt, "--out", tmp_path / out, *topics)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("hil export: error: ") and done.stderr.count("\n") == 1
    assert not (tmp_path / "new").exists(), "the refused log left a new folder"


def test_an_existing_file_as_out_folder_is_still_refused_first(tmp_path: Path) -> None:
    """The checks that create nothing still come before the log is read."""
    (tmp_path / "taken").write_text("a file")
    done = hil("export", tmp_path / "missing.mcap", "--format", "csv", "--out", tmp_path / "taken")
    assert done.returncode == 2
    assert "is a file, not a directory" in done.stderr, done.stderr
