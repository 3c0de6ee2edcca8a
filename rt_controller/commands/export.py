"""``hil export``: a controller log's tables as CSV, Parquet or MATLAB ``.mat``."""

from __future__ import annotations

import argparse
from pathlib import Path

from hal import strict_json
from hal.arguments import path_given

TOPIC_NAMES = ("cycle", "diagnostics", "can", "canopen")
DEFAULT_TOPICS = ("cycle", "diagnostics", "can")

DESCRIPTION = """\
Writes the tables of a controller log (MCAP), as rt_controller.logs.load gives them: cycle (one
row per tick; vectors as columns q1, q2, dq1, f_x, f_y, tau1, ...), diagnostics (one row per
/diagnostics record, every counter a column) and can (every raw CAN frame, decoded with the
DBC: time, direction, frame id, message, one column per signal; a cia402 log's CANopen frames
by COB-ID). canopen, only when asked for: a cia402 log's /hal/canopen topic as recorded (the
frames decoded by the recorder: kind, node, the decoded fields as columns).

The can table's integer signals (Tick, Counter, Enable, an enumerated signal's raw value)
are integers, as in rt_controller.logs.load(...).can_frames: parquet int64 columns, csv digits
(4294967295, not 4294967295.0); where a frame lacks the signal, a null and an empty cell. mat
has no missing integer: doubles, NaN there.

csv and parquet write one file per topic, LOGSTEM.TOPIC.csv (.parquet); mat writes one file,
LOGSTEM.mat, with a struct per topic (fields: the columns) and a meta struct (the recorded
configuration as JSON, its digest, the hil.run metadata). --out DIR puts them in DIR (default:
the log's directory; created if missing); an --out ending in the format's suffix is the file
itself (for csv and parquet with one --topics). An --out ending in another format's suffix
(--format mat --out m.csv) is refused: a folder of that name is not what it says. Existing
files of these names are replaced (an export is made again from its log at any time). Needs
the analysis extra: pip install 'hil-rhc-visual-servo[analysis]'.
"""


def topic_list(text: str) -> tuple[str, ...]:
    topics = tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))
    bad = [t for t in topics if t not in TOPIC_NAMES]
    if bad or not topics:
        raise argparse.ArgumentTypeError(
            f"unknown topic(s) {', '.join(bad) or '(none)'}: choose from {', '.join(TOPIC_NAMES)}"
        )
    return topics


def check_not_a_file_name(out: str, fmt: str) -> None:
    """Refuse a folder ``--out`` named like another format's file (``--format mat --out
    m.csv`` would make a folder ``m.csv``), unless that folder exists already or ``out`` ends
    in a slash."""
    from rt_controller.errors import OutputPathError
    from rt_controller.logs.export import SUFFIXES

    suffix = Path(out).suffix.lower()  # m.CSV names a CSV file too
    if out.endswith("/"):  # x.csv/ says folder
        return
    if suffix in SUFFIXES.values() and not Path(out).is_dir():
        raise OutputPathError(
            f"--out {out}: names a {suffix} file, but --format {fmt} writes {SUFFIXES[fmt]} "
            f"files: give a folder, or a file name ending in {SUFFIXES[fmt]}"
        )


def check_not_the_log(log: str, out: str | None, files: dict[str, Path]) -> None:
    """Refuse an output file that is the log itself (``--out`` naming it, or ``LOG.mat``
    exported with ``--format mat`` beside it): an export replaces its files, never its log."""
    from rt_controller.errors import OutputPathError
    from rt_controller.logtools.reader import same_file

    for path in set(files.values()):
        if Path(log).exists() and same_file(path, log):  # a missing log is told when read
            option = "--out" if out is not None else "the default output file"
            raise OutputPathError(
                f"{option} {path}: is the log being exported ({log}); an export never "
                "overwrites its log: give another --out"
            )


def check_outputs(out: str | None, fmt: str, files: dict[str, Path], *, make: bool) -> None:
    """Check the output paths with the commands' rule. ``make=False`` runs only the checks
    that create nothing (before the log is read: a bad log must leave no new folder);
    ``make=True`` runs them all, creating the missing folders."""
    from rt_controller.commands.output import output_dir, output_file

    if out is not None and not set(files.values()) & {Path(out)}:
        check_not_a_file_name(out, fmt)
        if make or creates_nothing(Path(out)):
            output_dir(out, "--out")
    option = "--out" if out is not None else "output file"  # beside LOG, no --out given
    for path in set(files.values()):
        if make or creates_nothing(path.parent):  # derived from the log: replaced at will
            output_file(path, option, replace=True)


def creates_nothing(folder: Path) -> bool:
    """Whether checking ``folder`` creates nothing: it exists, or making it fails at its
    nearest existing ancestor (a file, a folder this process cannot write)."""
    import os

    base = folder
    while not base.exists() and base != base.parent:
        base = base.parent
    return base == folder or not base.is_dir() or not os.access(base, os.W_OK)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write a log's tables as CSV, Parquet or MATLAB .mat",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("log", metavar="LOG.mcap", help="controller log")
    p.add_argument("--format", required=True, choices=("csv", "parquet", "mat"), help="format")
    p.add_argument(
        "--topics",
        type=topic_list,
        default=DEFAULT_TOPICS,
        metavar="LIST",
        help=f"comma-separated tables to write, of {','.join(TOPIC_NAMES)} "
        f"(default: {','.join(DEFAULT_TOPICS)})",
    )
    p.add_argument(
        "--out",
        type=path_given,
        metavar="PATH",
        help="output directory, or a file ending in the format's suffix (default: beside LOG); "
        "existing files are replaced",
    )
    p.add_argument("--json", action="store_true", help="print the files written as JSON")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from rt_controller.commands.interrupts import run_interruptible
    from rt_controller.logs.export import plan_outputs

    files = plan_outputs(args.log, args.format, args.topics, args.out)  # before any work:
    paths = list(dict.fromkeys(files.values()))  # in the order they are written
    existed = {p: p.exists() for p in paths}
    done: list[Path] = []

    def left() -> str:
        wrote = f"wrote {', '.join(map(str, done))}" if done else "no file written"
        return wrote + _not_written([p for p in paths if p not in done], existed)

    return run_interruptible("hil export", lambda: _run(args, files, done), left)


def _not_written(paths: list[Path], existed: dict[Path, bool]) -> str:
    """``; not written: A, B`` (each file there before is as it was)."""
    from rt_controller.commands.interrupts import unwritten

    if not paths:
        return ""
    kept = " (a file there before is as it was)" if any(existed[p] for p in paths) else ""
    for p in paths:
        unwritten(p, False)  # removes a temporary file left beside it
    return f"; not written: {', '.join(map(str, paths))}{kept}"


def _run(args: argparse.Namespace, files: dict[str, Path], done: list[Path]) -> int:
    """The export of ``files``; each file's path is added to ``done`` once written whole."""
    from rt_controller.errors import LogError
    from rt_controller.logs import load
    from rt_controller.logs.export import export
    from rt_controller.logtools.replay_out import inherited_loss

    check_not_the_log(args.log, args.out, files)
    check_outputs(args.out, args.format, files, make=False)  # what exists, creating nothing
    run_ = load(args.log, raw=bool({"can", "canopen"} & set(args.topics)))
    if "cycle" in args.topics and run_.log.n_cycles == 0:  # as replay: no empty tables
        why = f" ({run_.notes[0]})" if run_.notes else ""
        what = f"no readable /controller/cycle messages{why}, nothing to export"
        raise LogError(f"{run_.path}: {what}")
    check_outputs(args.out, args.format, files, make=True)  # the log is good: make folders
    written = []
    for path in dict.fromkeys(files.values()):  # file by file: an interrupt names those done
        written += export(run_, args.format, {t: p for t, p in files.items() if p == path})
        done.append(path)
    notes = list(run_.notes)
    lost = inherited_loss(run_.log)  # a whole file holding part of a run: say so
    if lost:
        notes.append(lost)
    if "canopen" in args.topics and not any(w.rows for w in written if w.topic == "canopen"):
        notes.append(
            f"{run_.path} has no /hal/canopen messages: only a cia402 run records them "
            '(hardware.profile = "cia402"); its CAN frames are in the can table'
        )
    if args.json:
        rows = [{"topic": w.topic, "path": str(w.path), "rows": w.rows} for w in written]
        summary = {"log": str(run_.path), "format": args.format, "files": rows}
        print(strict_json.dumps({**summary, "truncated": run_.truncated, "notes": notes}))
        return 0
    for w in written:
        print(f"{w.topic}: {w.rows} rows -> {w.path}")
    for note in notes:
        print(f"note: {note}")
    return 0
