"""``hil recover``: a finished copy of a log whose recorder was killed or that was cut."""

from __future__ import annotations

import argparse

from hal import strict_json
from hal.arguments import path_given

DESCRIPTION = """\
Reads LOG.mcap up to its last complete record (mcap's stream reader; past a damaged chunk in
the middle when the file still has its summary, whose chunk index says where the next one
starts) and writes every schema, channel, message, metadata and attachment again with mcap's
writer, with chunk indexes, a summary section and the footer: a log whose recorder was
SIGKILLed, or a file cut or damaged in a copy, then opens in mcap's own reader and in Foxglove.
A hil.recovered metadata record in the copy names the input and what was kept; `hil info`
shows it. The input is never changed (an --out naming it, or a device or FIFO, is refused);
an existing copy (--out or the default name) is refused unless --force.
Prints one line with what was kept and what was lost (the bytes after the last complete
record, usually a half-written chunk, and the damaged chunks skipped). A cut or damaged log
without one message that can be read (cut inside its first chunk) gives no copy: one line
saying where the read stopped, exit 1.

--json prints one object: log, out, finished (the input already had its footer), input_bytes,
kept_bytes, lost_bytes, skipped (the damaged chunks stepped over: offset, length, error),
stopped (why the read ended), messages, cycles, schemas, channels, metadata (names),
attachments, topics ({TOPIC: messages}), orphans (messages without a channel record,
skipped).
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "recover",
        help="write a finished copy of a cut log (recorder killed) that stock MCAP tools open",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("log", metavar="LOG.mcap", help="the cut log (read only)")
    p.add_argument(
        "--out",
        type=path_given,
        metavar="NEW.mcap",
        help="the copy (default: LOG.recovered.mcap beside LOG)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing copy")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    from rt_controller.commands.interrupts import run_interruptible, unwritten
    from rt_controller.commands.output import output_file
    from rt_controller.logtools.reader import same_file
    from rt_controller.logtools.recover import NothingRecovered, default_out, recover

    given = args.out or default_out(Path(args.log))
    option = "--out" if args.out else "the default --out"
    out = Path(given)
    existed, done = out.exists(), []

    def body() -> int:
        if args.out or Path(args.log).exists():  # no folder made for a missing log's default
            # the input itself is refused by recover, whatever --force says
            output_file(given, option, replace=args.force or same_file(out, args.log))
        try:
            result = recover(args.log, out)
        except NothingRecovered as exc:  # a runtime failure (exit 1), not a bad argument
            print(f"hil recover: error: {exc}", file=sys.stderr)
            return 1
        done.append(True)
        print(strict_json.dumps(result.as_dict()) if args.json else result.line())
        return 0

    def left() -> str:
        return f"{out} was written whole" if done else f"the copy {unwritten(out, existed)}"

    return run_interruptible("hil recover", body, left)
