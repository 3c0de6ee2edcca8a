"""The CAN pages: ``dbc.md`` (every message and signal of ``hal/hil.dbc``, read with cantools)
and ``cia402-od.md`` (the emulated CiA 402 drive's object dictionary, read from its EDS)."""

from __future__ import annotations

import re
from pathlib import Path

from docgen.markdown import HEADER, ROOT, code, esc, heading, slug


def dbc_page() -> str:
    import cantools

    path = ROOT / "hal" / "hil.dbc"
    db = cantools.database.load_file(str(path))
    md = [
        HEADER.format(source="hal/hil.dbc (cantools)"),
        "# CAN database reference\n\n",
        "The rig's CAN messages as `hal/hil.dbc` defines them, the single source of truth that ",
        "the codec is compiled from. What the frames mean and how they are protected: ",
        "[CAN frames and E2E](../concepts/can.md) and [SecOC](../concepts/secoc.md).\n\n",
    ]
    comment = _dbc_database_comment(path)
    if comment:
        md.append(f"{esc(comment)}\n\n")
    md.append("Nodes: " + ", ".join(f"`{n.name}` ({esc(n.comment or '')})" for n in db.nodes))
    md.append("\n\n| id | message | sender → receivers | length | cycle | E2E data id |\n")
    md.append("|---|---|---|---|---|---|\n")
    for m in sorted(db.messages, key=lambda m: m.frame_id):
        md.append(_message_row(m))
    md.append("\n")
    for m in sorted(db.messages, key=lambda m: m.frame_id):
        md.append(heading(2, m.name))
        if m.comment:
            md.append(f"{esc(m.comment)}\n\n")
        fd = "CAN FD" if m.is_fd else "classic CAN"
        md.append(f"Id `0x{m.frame_id:03X}`, {m.length} bytes, {fd}.\n\n")
        md.append(
            "| signal | start \\| length | type | scale | offset | min | max | unit | meaning |\n"
            "|---|---|---|---|---|---|---|---|---|\n"
        )
        for s in sorted(m.signals, key=lambda s: s.start):
            kind = ("signed" if s.is_signed else "unsigned") + (
                "" if s.byte_order == "little_endian" else ", big-endian"
            )
            meaning = s.comment or ""
            if s.choices:
                meaning += " Values: " + ", ".join(f"{int(k)} = {v}" for k, v in s.choices.items())
            md.append(
                f"| `{s.name}` | {s.start} \\| {s.length} | {kind} | {s.scale:g} | {s.offset:g} "
                f"| {_num(s.minimum)} | {_num(s.maximum)} | {esc(s.unit or '')} "
                f"| {esc(meaning)} |\n"
            )
        md.append("\n")
    return "".join(md).rstrip() + "\n"


def _num(x: float | None) -> str:
    return "" if x is None else f"{x:g}"


def _dbc_database_comment(path: Path) -> str:
    m = re.search(r'^CM_ "((?:[^"\\]|\\.)*)";', path.read_text(encoding="utf-8"), re.M)
    return m.group(1) if m else ""


def _message_row(m: object) -> str:
    attrs = m.dbc.attributes if m.dbc else {}
    data_id = attrs.get("E2EDataID")
    cycle = f"{m.cycle_time} ms" if m.cycle_time else "on event"
    receivers = ", ".join(sorted({r for s in m.signals for r in s.receivers}))
    return (
        f"| `0x{m.frame_id:03X}` | [`{m.name}`](#{slug(m.name)}) "
        f"| {', '.join(m.senders)} → {receivers} | {m.length} | {cycle} "
        f"| {'' if data_id is None else f'`0x{data_id.value:04X}`'} |\n"
    )


_ACCESS = {
    "ro": "read",
    "wo": "write",
    "rw": "read/write",
    "rww": "read/write",
    "rwr": "read/write",
}


def _od_default(var: object) -> str:
    raw = getattr(var, "default_raw", None)
    if raw is not None and "$NODEID" in str(raw):
        return code(str(raw).replace("$NODEID", "node id"))
    value = getattr(var, "default", None)
    if isinstance(value, int) and var.data_type in (5, 6, 7) and value > 9:  # UNSIGNED8/16/32
        return code(f"0x{value:X}")
    return "" if value is None else code(value)


def cia402_od_page() -> str:
    """The emulated CiA 402 drive's object dictionary, read back from the shipped EDS."""
    import canopen
    from canopen.objectdictionary import ODVariable, datatypes

    from hal.cia402_od import EDS_PATH

    od = canopen.import_od(str(EDS_PATH))
    types = {getattr(datatypes, n): n for n in dir(datatypes) if n.isupper() and n[:1] in "IUVB"}
    md = [
        HEADER.format(source="hal/cia402_drive.eds (written by hal/cia402_od.py)"),
        heading(1, "CiA 402 object dictionary"),
        "The objects of the emulated CiA 402 servo drive (`hil emulator --profile cia402`), "
        "read with canopen's `import_od` from the EDS the emulator ships "
        "(`hal/cia402_drive.eds`, generated from the one table in `hal/cia402_od.py`). A real "
        "drive's EDS lists these objects too; its values (rated torque, encoder resolution) come "
        "from its manual. Defaults relative to the node id are written `node id+0x...`; PDO "
        "COB-IDs with bit 31 (0x80000000) set are disabled.\n\n",
        "| index | sub | name | type | access | PDO | default | unit |\n",
        "|---|---|---|---|---|---|---|---|\n",
    ]
    for index in sorted(od.indices):
        obj = od[index]
        members = [obj] if isinstance(obj, ODVariable) else [obj[s] for s in sorted(obj.subindices)]
        if not isinstance(obj, ODVariable):
            md.append(f"| `0x{index:04X}` |  | **{esc(obj.name)}** |  |  |  |  |  |\n")
        for var in members:
            sub = "" if isinstance(obj, ODVariable) else str(var.subindex)
            md.append(
                f"| `0x{index:04X}` | {sub} | {esc(var.name)} | {types.get(var.data_type, '?')} | "
                f"{_ACCESS.get(var.access_type, var.access_type)} | "
                f"{'yes' if var.pdo_mappable else ''} | {_od_default(var)} | {esc(var.unit)} |\n"
            )
    return "".join(md)
