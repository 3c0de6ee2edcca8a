"""``hil cia402 check``: boot the CiA 402 drives of ``[cia402]`` as a ``cia402`` run would
(NMT reset, SDO configuration, PDO maps read back, cyclic synchronous torque read back) and
say what each drive reports, without a SYNC and without enabling any drive."""

from __future__ import annotations

import argparse
import sys

from hal import strict_json
from rt_controller.commands.common import add_config_option, add_set_option, config_from_args


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cia402",
        help="CiA 402 drives (the cia402 profile): check the boot and the mapping",
        description="`check` boots every drive of [cia402] exactly as a cia402 run does (NMT "
        "reset communication, heartbeats, 0x60C2, 0x6072, the PDO maps read back, mode 10 read "
        "back in 0x6061), each drive described by its EDS (cia402.eds_1, eds_2: the vendor's file; "
        "the shipped one when empty), prints what each drive reports (state, units, limits, "
        "maps, the EDS it was given), then puts "
        "the drives in NMT pre-operational and stops consuming the controller's heartbeat. It "
        "sends no SYNC and never enables a drive: run it before a real drive gets torque. Exit "
        "2 when a drive does not boot or refuses a step.",
    )
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    check = actions.add_parser("check", help="boot, map and describe the drives; no torque")
    add_config_option(check)
    add_set_option(check)
    check.add_argument(
        "--can", metavar="INTERFACE[:CHANNEL]", help="CAN bus (default: transport.can)"
    )
    check.add_argument("--json", action="store_true", help="one JSON object on stdout")
    check.set_defaults(handler=run_check)


VIRTUAL_NOTE = (
    "on python-can's virtual bus only drives in this process can answer, none in another: "
    "use udp_multicast (this host) or socketcan:CHANNEL"
)
"""Said at the start of a check on ``virtual`` (open to this command for the drives a test
runs in its own process)."""


def eds_label(value: str) -> str:
    """The EDS a ``cia402.eds_N`` value gives a drive, as the command names it."""
    return value or "the shipped hal/cia402_drive.eds"


def run_check(args: argparse.Namespace) -> int:

    from hal.bus import open_bus, resolve_spec
    from hal.cia402_master.eds import configured
    from hal.cia402_master.master import Cia402Master

    cfg = config_from_args(args)
    given = {node: (key, eds_label(value)) for key, value, node in configured(cfg)}
    bus = open_bus(args.can or cfg.transport.can, bitrate=cfg.cia402.bitrate, fd=False)
    master = Cia402Master.from_config(cfg, bus)
    nodes = " and ".join(f"node {n} (EDS {label})" for n, (_key, label) in given.items())
    virtual = resolve_spec(args.can or cfg.transport.can).interface == "virtual"

    def waiting() -> None:  # a drive may take many seconds: say what for, not only at its end
        print(
            f"hil cia402 check: NMT reset communication sent, waiting up to "
            f"{master.settings.boot_timeout_s:g} s for the boot-up of {nodes}"
            + (f" ({VIRTUAL_NOTE})" if virtual else ""),
            file=sys.stderr,
            flush=True,
        )

    try:
        drives = master.check(on_wait=waiting)
    finally:
        master.close()
    for d in drives:
        d["eds"] = given[d["node"]][1]
    if args.json:
        print(strict_json.dumps({"drives": drives}))
        return 0
    for d in drives:
        pdo = "; ".join(
            f"{kind}{n} = {' + '.join(objs)}"
            for kind, maps in d["pdo"].items()
            for n, objs in maps.items()
        )
        print(
            f"node {d['node']}: {d['state']} (statusword {d['statusword']}), mode "
            f"{d['mode_display']}, {d['increments_per_rad']:.6g} increments/rad, rated "
            f"{d['rated_torque_nm']:g} N·m, limit {d['torque_limit_nm']:g} N·m "
            f"({d['torque_limit_per_mille']} per mille), 0x60C2 "
            f"{d['interpolation_period_s'] * 1e3:g} ms, heartbeat {d['heartbeat_ms']} ms; {pdo}; "
            f"EDS {d['eds']}"
        )
    print("hil cia402 check: drives left in NMT pre-operational, not enabled", file=sys.stderr)
    return 0
