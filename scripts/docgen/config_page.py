"""``config.md``: every configuration key with its default, range and meaning, from the
dataclasses of ``hal/config/`` (attribute docstrings, else the comment of the key in
``examples/rig.toml``) and ``hal.config.ranges.RANGES``."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
import typing
from pathlib import Path

from docgen.markdown import HEADER, ROOT, code, esc, with_next


def _attribute_docs(source: Path) -> dict[str, dict[str, str]]:
    """``{class name: {field: docstring}}`` of the classes of ``source``, plus ``"__doc__"``."""
    docs: dict[str, dict[str, str]] = {}
    for node in ast.parse(source.read_text(encoding="utf-8")).body:
        if not isinstance(node, ast.ClassDef):
            continue
        fields = {"__doc__": ast.get_docstring(node) or ""}
        for stmt, nxt in with_next(node.body):
            if (
                isinstance(stmt, ast.AnnAssign)
                and isinstance(stmt.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                fields[stmt.target.id] = nxt.value.value
        docs[node.name] = fields
    return docs


def _toml_comments(path: Path) -> dict[str, str]:
    """``{"section.key": comment}`` from the inline comments of ``examples/rig.toml``, and
    ``{"section": comment}`` from the comments on its section headers."""
    comments: dict[str, str] = {}
    section = ""
    for line in path.read_text(encoding="utf-8").splitlines():
        body, _, comment = line.partition("#")
        body, comment = body.strip(), comment.strip()
        if m := re.fullmatch(r"\[([A-Za-z_]+)\]", body):
            section = m.group(1)
            if comment:
                comments[section] = comment
        elif (m := re.match(r"([A-Za-z_0-9]+)\s*=", body)) and comment:
            comments[f"{section}.{m.group(1)}"] = comment
    return comments


def _type_name(hint: object) -> str:
    from hal.config import Mat2, Vec2

    if hint == Vec2:
        return "[float, float]"
    if hint == Mat2:
        return "2x2 matrix"
    return getattr(hint, "__name__", str(hint))


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def _range(entry: tuple[float, float, str] | None) -> str:
    if entry is None:
        return ""
    lo, hi, kind = entry
    return code(f"{kind[0]}{lo:g}, {hi:g}{kind[1]}")


def config_page() -> str:
    from hal import config
    from hal.config.ranges import RANGES

    docs: dict[str, dict[str, str]] = {}
    for module in sorted((ROOT / "hal" / "config").glob("*.py")):
        docs.update(_attribute_docs(module))
    comments = _toml_comments(ROOT / "examples" / "rig.toml")
    md = [
        HEADER.format(source="hal/config/ (dataclasses, ranges.py) and examples/rig.toml"),
        "# Configuration reference\n\n",
        "Every key of the rig's TOML file (`--config FILE`), with its embedded default, the range ",
        "`hal.config` validates it against (each element of a vector or matrix; `[` closed, `(` ",
        "open) and its meaning. Any key may be omitted; an unknown key, a wrong type or a value ",
        "out of range is refused at start-up in one line naming the key. ",
        "`examples/rig.toml` lists the same keys with the same defaults. How the file, the ",
        "`--set` overrides and the options combine: [Configuration](../concepts/configuration.md).",
        "\n\n",
        "Control laws (`controller.law`, `--law`): ",
        ", ".join(f"`{n}`" for n in config.LAW_NAMES),
        ".\n\n",
    ]
    ranges = RANGES
    for section, cls in typing.get_type_hints(config.RigConfig).items():
        if not dataclasses.is_dataclass(cls):
            continue
        cdocs = docs.get(cls.__name__, {})
        md.append(f"## [{section}]\n\n")
        intro = cdocs.get("__doc__") or comments.get(section, "")
        if intro:
            md.append(f"{esc(intro)}\n\n")
        md.append("| key | type | default | range | meaning |\n|---|---|---|---|---|\n")
        hints = typing.get_type_hints(cls)
        defaults = cls()
        for f in dataclasses.fields(cls):
            key = f"{section}.{f.name}"
            meaning = cdocs.get(f.name) or comments.get(key, "")
            md.append(
                f"| {code(key)} | {esc(_type_name(hints[f.name]))} "
                f"| {code(_toml_value(getattr(defaults, f.name)))} | {_range(ranges.get(key))} "
                f"| {esc(meaning)} |\n"
            )
        md.append("\n")
    return "".join(md).rstrip() + "\n"
