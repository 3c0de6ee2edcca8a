"""The package installed without any extra, as ``pip install hil-rhc-visual-servo`` gives it:
every subcommand's ``--help`` works, and a minimal call of each either succeeds or fails with one
line (the extra it needs and the pip command, exit 2; or why it cannot run alone), never with a
traceback.

The subcommands come from ``cli.COMMAND_MODULES`` and the parser itself, so a new command is
covered the day it is added (and this test asks for its minimal call in :func:`minimal_calls`).
Needs PyPI (or pip's cache) for the core dependencies; the fresh venv is built once per module.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from rt_controller.cli import COMMAND_MODULES, build_parser
from rt_controller.extras import EXTRAS, install_command

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.timeout(1800)]

ROOT = Path(__file__).resolve().parents[2]


def sources() -> list[Path]:
    """What the package is built from: ``pyproject.toml``, the readme and the top-level
    packages its ``packages.find`` includes."""
    import fnmatch
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = project["tool"]["setuptools"]["packages"]["find"]["include"]
    found = [
        d
        for d in sorted(ROOT.iterdir())
        if (d / "__init__.py").is_file() and any(fnmatch.fnmatch(d.name, p) for p in include)
    ]
    return [ROOT / "pyproject.toml", ROOT / project["project"]["readme"], *found]


EXTRA_MODULES = sorted({m for mods in EXTRAS.values() for m in mods})

OK, EXTRA, ALONE = "ok", "extra", "alone"
"""Expected outcomes: success; the one-line missing-extra error (exit 2); a one-line error
because the command needs a running rig (covered with one by ``hil up``, whose children are
the same commands)."""


@dataclass(frozen=True)
class Call:
    argv: tuple[str, ...]
    outcome: str
    extra: str | None = None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def minimal_calls(work: Path) -> dict[str, Call]:
    """One small call per subcommand (``bench``: per bench), run from ``work``."""
    log, key, ep = "run.mcap", "rig.key", f"tcp/127.0.0.1:{free_port()}"
    return {
        "keygen": Call(("keygen", key), OK),
        "up": Call(("up", "--lockstep", "--duration", "1", "--log", log, "--json"), OK),
        "emulator": Call(
            ("emulator", "--duration", "1", "--key-file", key, "--zenoh-endpoint", ep), OK
        ),
        "vision": Call(
            ("vision", "--duration", "1", "--wait", "1", "--key-file", key, "--zenoh-endpoint", ep),
            ALONE,
        ),
        "controller": Call(
            ("controller", "--duration", "1", "--no-rt", "--key-file", key, "--zenoh-endpoint", ep),
            ALONE,
        ),
        "monitor": Call(
            ("monitor", "--duration", "1", "--key-file", key, "--zenoh-endpoint", ep), ALONE
        ),
        "param": Call(
            ("param", "get", "--timeout", "1", "--key-file", key, "--zenoh-endpoint", ep), ALONE
        ),
        "camera": Call(("camera", "calibrate", "--source", "emulated", "--json"), OK),
        "cia402": Call(("cia402", "check", "--can", "virtual:no-drives"), ALONE),
        "simulate": Call(("simulate", "--duration", "0.2", "--json"), OK),
        "replay": Call(("replay", log, "--json"), OK),
        "report": Call(("report", log, "--plot", "plots", "--json"), OK),
        "info": Call(("info", log, "--json"), OK),
        "recover": Call(("recover", log, "--out", "recovered.mcap", "--json"), OK),
        "export": Call(("export", log, "--format", "parquet"), EXTRA, "analysis"),
        "experiment": Call(("experiment", "fig3", "--reps", "1", "--out", "exp"), EXTRA, "sweep"),
        "sweep": Call(("sweep", str(ROOT / "examples" / "robustness.toml")), EXTRA, "sweep"),
        "bench host": Call(("bench", "host", "--duration", "0.5"), OK),
        "bench sweep": Call(("bench", "sweep", "--runs", "1"), EXTRA, "sweep"),
        "bench soak": Call(
            ("bench", "soak", "--duration", "3", "--sample", "1", "--warmup", "1"), OK
        ),
    }


def subcommands() -> list[tuple[str, ...]]:
    """Every subcommand of the parser, nested ones (``bench host``) included."""

    def walk(parser: argparse.ArgumentParser, prefix: tuple[str, ...]) -> list[tuple[str, ...]]:
        found = []
        for action in parser._actions:  # argparse offers no public walk of its sub-parsers
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    found += [(*prefix, name), *walk(sub, (*prefix, name))]
        return found

    return walk(build_parser(), ())


@dataclass(frozen=True)
class Core:
    hil: Path
    python: Path
    work: Path

    def run(self, *argv: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        env["PATH"] = f"{self.hil.parent}{os.pathsep}{env.get('PATH', '')}"
        return subprocess.run(
            [str(self.hil), *argv],
            cwd=self.work,
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )


@pytest.fixture(scope="module")
def core(tmp_path_factory: pytest.TempPathFactory) -> Core:
    base = tmp_path_factory.mktemp("core")
    src = base / "src"
    src.mkdir()
    for path in sources():  # a copy: pip builds in the tree it installs from
        if path.is_dir():
            shutil.copytree(path, src / path.name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / path.name)
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    pip = subprocess.run(
        [str(python), "-m", "pip", "install", "--disable-pip-version-check", str(src)],
        capture_output=True,
        text=True,
        timeout=1500,
    )
    assert pip.returncode == 0, pip.stdout[-3000:] + pip.stderr[-3000:]
    work = base / "work"
    work.mkdir()
    return Core(venv / "bin" / "hil", python, work)


def test_the_core_install_holds_no_extra(core: Core):
    probe = (
        "import importlib.util, sys; "
        f"print([m for m in {EXTRA_MODULES!r} if importlib.util.find_spec(m)])"
    )
    out = subprocess.run([str(core.python), "-c", probe], capture_output=True, text=True)
    assert out.stdout.strip() == "[]", out


@pytest.mark.parametrize("command", subcommands(), ids=" ".join)
def test_help_of_every_subcommand(core: Core, command: tuple[str, ...]):
    done = core.run(*command, "--help", timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: hil {' '.join(command)}")
    assert "Traceback" not in done.stderr


def test_every_subcommand_has_a_minimal_call(core: Core):
    calls = minimal_calls(core.work)
    covered = {name.split()[0] for name in calls}
    missing = set(COMMAND_MODULES) - covered
    assert not missing, f"add to minimal_calls: {missing}"


ORDER = ("keygen", "up")  # the rig key and the log the other calls use


@pytest.mark.parametrize(
    "name",
    sorted(
        minimal_calls(Path()), key=lambda n: (n not in ORDER, ORDER.index(n) if n in ORDER else 0)
    ),
)
def test_minimal_call(core: Core, name: str):
    call = minimal_calls(core.work)[name]
    if name != "up" and "run.mcap" in call.argv and not (core.work / "run.mcap").exists():
        pytest.fail("hil up in the core install wrote no log (see test_minimal_call[up])")
    done = core.run(*call.argv)
    assert "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if ": error: " in line]
    if call.outcome == OK:
        assert done.returncode == 0, done.stderr
        assert not errors
        return
    assert len(errors) == 1, done.stderr
    if call.outcome == EXTRA:
        assert done.returncode == 2, done.stderr
        assert f"'{call.extra}' extra" in errors[0] and install_command(call.extra) in errors[0]
    else:
        assert done.returncode in (1, 2), done.stderr
