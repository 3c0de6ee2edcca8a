"""How subcommands print their summaries and check where they write (shared by the command
modules, not by ``cli``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hal import strict_json


def stdout_console() -> Any:
    """rich's Console on stdout, whose reader gone (``| head``) raises the BrokenPipeError
    every command ends on with SIGPIPE's status (:func:`hal.signals.run_standalone`); rich's
    own answer is a silent exit 1."""
    import errno

    from rich.console import Console

    class PipedConsole(Console):
        def on_broken_pipe(self) -> None:
            self.quiet = True  # nothing more is written; the exit's flush is run_standalone's
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    return PipedConsole()


def print_summary(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """One JSON object on stdout, or a two-column table for people."""
    if as_json:
        print(strict_json.dumps(summary))
        return
    from rich.table import Table

    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        if isinstance(value, float):
            text = f"{value:.6g}"
        elif isinstance(value, list):
            text = ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in value)
            text = text or "none"  # an empty list (no problems) is not a blank cell
        else:
            text = str(value)
        table.add_row(key, text)
    stdout_console().print(table)


def print_summary_with_notes(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """:func:`print_summary` for a summary with a ``notes`` list: notes as lines after the table."""
    if as_json:
        print(strict_json.dumps(summary))
        return
    notes = summary.pop("notes")
    print_summary(summary, False, title)
    for note in notes:
        print(f"note: {note}")


def verdict(summary: dict[str, Any], title: str) -> int:
    """A finished run's warnings and problems on stderr; its exit status (1: not clean)."""
    import sys

    for warning in summary.get("warnings") or []:
        print(f"{title}: warning: {warning}", file=sys.stderr)
    problems = summary.get("problems") or []
    if problems:
        print(f"{title}: run not clean: {'; '.join(problems)}", file=sys.stderr)
        return 1
    return 0


def output_dir(path: str | Path, option: str) -> Path:
    """The folder ``path`` given with ``option`` (e.g. ``--plot``), created if missing and
    checked writable, before the command starts its work.

    Raises :class:`~rt_controller.errors.OutputPathError`, one line naming the option, the path
    and why: a file where a folder is wanted, a folder that cannot be created (under a file,
    under ``/proc``, no permission) or cannot be written (read-only file system)."""
    import tempfile

    from rt_controller.errors import OutputPathError

    out = Path(path)
    where = f"{option} {path}"
    if out.exists() and not out.is_dir():
        raise OutputPathError(f"{where}: is a file, not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputPathError(f"{where}: cannot create the directory: {_why(exc, out)}") from None
    try:
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise OutputPathError(f"{where}: cannot write into it: {_why(exc, out)}") from None
    return out


def output_file(path: str | Path, option: str, *, replace: bool = True) -> Path:
    """The file ``path`` given with ``option`` (e.g. ``--out``): not empty, not a folder (nor
    named as one, ending in a slash), a device or a FIFO, in a folder that :func:`output_dir`
    accepts (created if missing). The file itself is not created.

    ``replace=False`` (a run's log, a log written by replay or recover: data that cannot be
    made again) also refuses a path that exists, naming ``--force``; derived outputs that
    are made again from their source (an export, a parameter dump) keep the default."""
    from rt_controller.errors import OutputPathError

    if not str(path):
        raise OutputPathError(f"{option}: the path is empty")
    if str(path).endswith("/"):  # Path() drops the slash: a file named as the folder
        raise OutputPathError(f"{option} {path}: ends in a slash, so names a folder; give a file")
    out = Path(path)
    if out.is_dir():
        raise OutputPathError(f"{option} {path}: is a directory, not a file")
    if out.exists() and not out.is_file():  # a device, a FIFO: it would swallow the file
        raise OutputPathError(f"{option} {path}: is not a regular file")
    if not replace and (out.exists() or out.is_symlink()):  # a dangling link: its target
        raise OutputPathError(f"{option} {path}: exists (pass --force to replace it)")
    parent = out.parent
    if parent.exists() and not parent.is_dir():
        raise OutputPathError(f"{option} {path}: {parent} is not a directory")
    try:
        output_dir(parent, option)
    except OutputPathError as exc:  # name the file, not only its folder
        raise OutputPathError(f"{option} {path}: {str(exc).split(': ', 1)[1]}") from None
    return out


def _why(exc: OSError, path: Path) -> str:
    """The OS's reason, and where: the nearest existing one of ``path`` and its ancestors
    (a file, for ``mkdir -p`` under a file; ``/proc``, which takes no new entries)."""
    reason = exc.strerror or str(exc)
    ancestor = next((p for p in (path, *path.parents) if p.exists()), None)
    if ancestor is not None and not ancestor.is_dir():
        return f"{ancestor} is not a directory"
    if ancestor is not None and isinstance(exc, FileNotFoundError | PermissionError):
        return f"{reason} (in {ancestor})"
    return reason
