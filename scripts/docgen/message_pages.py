"""The message pages: ``zenoh.md`` (the key expressions, ``KEY_*`` of ``hal/zenoh_session.py``)
and ``schemas.md`` (the JSON Schemas of the MCAP topics and live channels: ``*_SCHEMA`` dicts
and ``*schema*.json`` files of the packages)."""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

from docgen.markdown import HEADER, ROOT, esc, heading, slug, with_next


def _module_constants(path: Path, pattern: str) -> list[tuple[str, object, str]]:
    """Module-level ``NAME = literal`` of ``path`` whose name matches ``pattern``, with the
    attribute docstring that follows each."""
    body = ast.parse(path.read_text(encoding="utf-8")).body
    found = []
    for stmt, nxt in with_next(body):
        target = None
        if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1:
            target = stmt.targets[0]
        elif isinstance(stmt, ast.AnnAssign):
            target = stmt.target
        if not isinstance(target, ast.Name) or not re.fullmatch(pattern, target.id):
            continue
        try:
            value = ast.literal_eval(stmt.value)
        except ValueError:
            value = None
        doc = ""
        if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant):
            doc = str(nxt.value.value)
        found.append((target.id, value, doc))
    return found


def zenoh_page() -> str:
    path = ROOT / "hal" / "zenoh_session.py"
    keys = _module_constants(path, r"KEY_[A-Z_]+")
    endpoint = dict((n, v) for n, v, _ in _module_constants(path, r"DEFAULT_ENDPOINT"))
    md = [
        HEADER.format(source="hal/zenoh_session.py"),
        "# zenoh keys reference\n\n",
        "The key expressions the rig's processes publish and subscribe on (`hal.zenoh_session`). ",
        "They are part of the rig's external contract: a real camera or another viewer speaks ",
        "them. Payloads of the vision keys are authenticated with the rig key ",
        "([SecOC](../concepts/secoc.md#the-vision-link)).\n\n",
        "| key | constant | payload and direction |\n|---|---|---|\n",
    ]
    for name, value, doc in keys:
        md.append(f"| `{value}` | `hal.zenoh_session.{name}` | {esc(doc)} |\n")
    if endpoint.get("DEFAULT_ENDPOINT"):
        md.append(
            f"\nDefault endpoint: `{endpoint['DEFAULT_ENDPOINT']}` (the emulator listens, the "
            "others connect; `--zenoh-endpoint` or `--zenoh-config FILE` to change it; see "
            "[Two hosts over TLS](../tutorials/two-hosts.md)).\n"
        )
    return "".join(md).rstrip() + "\n"


# ------------------------------------------------------------------------------------ schemas


def find_schemas() -> list[tuple[str, str, dict]]:
    """``(file, name, schema)`` of every ``*_SCHEMA`` dict literal and ``*schema*.json`` file
    of the packages, by title."""
    found: dict[str, tuple[str, str, dict]] = {}
    for pkg in ("hal", "rt_controller", "plant_emulator"):
        for py in sorted((ROOT / pkg).rglob("*.py")):
            rel = py.relative_to(ROOT).as_posix()
            for name, value, _ in _module_constants(py, r"[A-Z_]*_SCHEMA"):
                if isinstance(value, dict) and "title" in value:
                    found.setdefault(value["title"], (rel, name, value))
        for js in sorted((ROOT / pkg).rglob("*schema*.json")):
            value = json.loads(js.read_text(encoding="utf-8"))
            rel = js.relative_to(ROOT).as_posix()
            found.setdefault(value.get("title", js.stem), (rel, js.name, value))
    return [found[t] for t in sorted(found)]


def _schema_type(prop: dict) -> str:
    t = prop.get("type", "")
    if t == "array" and isinstance(prop.get("items"), dict):
        inner = prop["items"].get("type", "")
        n = prop.get("minItems")
        return f"array of {inner}" + (f" ({n})" if n and n == prop.get("maxItems") else "")
    return t if isinstance(t, str) else " or ".join(t)


def schemas_page() -> str:
    md = [
        HEADER.format(source="the *_SCHEMA dicts and *schema*.json files of the packages"),
        "# JSON Schemas reference\n\n",
        "The JSON Schemas of the rig's JSON messages: the MCAP log's topics and the live ",
        "channels of `hil monitor` carry them, so Foxglove and Lichtblick plot the fields as ",
        "they are. Which topic carries which schema: [Logs and MCAP topics](../concepts/logs.md)",
        ".\n\n",
        "| schema | defined in |\n|---|---|\n",
    ]
    schemas = find_schemas()
    for path, name, schema in schemas:
        md.append(f"| [`{schema['title']}`](#{slug(schema['title'])}) | `{path}` (`{name}`) |\n")
    md.append("\n")
    for _path, _name, schema in schemas:
        md.append(heading(2, schema["title"]))
        if schema.get("description"):
            md.append(f"{esc(schema['description'])}\n\n")
        required = set(schema.get("required", []))
        md.append("| field | type | required | meaning |\n|---|---|---|---|\n")
        for field, prop in schema.get("properties", {}).items():
            md.append(
                f"| `{field}` | {esc(_schema_type(prop))} | {'yes' if field in required else ''} "
                f"| {esc(prop.get('description', ''))} |\n"
            )
        md.append(
            '\n??? note "The schema as JSON"\n\n    ```json\n'
            + "\n".join("    " + line for line in json.dumps(schema, indent=2).splitlines())
            + "\n    ```\n\n"
        )
    return "".join(md).rstrip() + "\n"
