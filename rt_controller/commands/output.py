"""How subcommands print their summaries (shared by the command modules, not by ``cli``)."""

from __future__ import annotations

import json
from typing import Any


def print_summary(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """One JSON object on stdout, or a two-column table for people."""
    if as_json:
        print(json.dumps(summary, sort_keys=False))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        if isinstance(value, float):
            text = f"{value:.6g}"
        elif isinstance(value, list):
            text = ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in value)
        else:
            text = str(value)
        table.add_row(key, text)
    Console().print(table)


def print_summary_with_notes(summary: dict[str, Any], as_json: bool, title: str) -> None:
    """:func:`print_summary` for a summary with a ``notes`` list: notes as lines after the table."""
    if as_json:
        print(json.dumps(summary))
        return
    notes = summary.pop("notes")
    print_summary(summary, False, title)
    for note in notes:
        print(f"note: {note}")
