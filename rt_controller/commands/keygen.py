"""``hil keygen FILE``: write a fresh rig key (mode 0600) for ``--key-file`` /
``transport.key_file``."""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "keygen",
        help="write a fresh rig key (authenticates CAN frames and vision messages)",
        description="Writes 32 random bytes as hex to FILE with mode 0600. Every process of one "
        "rig must load the same key (--key-file FILE or transport.key_file); `hil up` makes a "
        "fresh one per run unless given --key-file. Copy it to other hosts of the rig over a "
        "secure channel (scp) and keep it mode 0600: a process refuses a key that group or "
        "others can read.",
    )
    p.add_argument("file", metavar="FILE", help="where to write the key")
    p.add_argument("--force", action="store_true", help="replace an existing file")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hal.secoc import write_key_file

    path = write_key_file(args.file, overwrite=args.force)
    print(f"hil keygen: wrote a rig key to {path} (mode 0600)", file=sys.stderr)
    return 0
