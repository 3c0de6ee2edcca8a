"""``cli.md``: every ``hil`` subcommand and option, walked from the argparse parsers of
``rt_controller.cli.build_parser()``."""

from __future__ import annotations

import argparse
import os
import textwrap

from docgen.markdown import HEADER, code, esc, heading, slug


def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            seen: set[int] = set()
            for name, sub in action.choices.items():
                if id(sub) in seen:  # an alias
                    continue
                seen.add(id(sub))
                out.append((name, helps.get(name, ""), sub))
    return out


def walk_cli(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ("hil",)
) -> list[tuple[tuple[str, ...], str, argparse.ArgumentParser]]:
    """Every parser under ``parser``, depth first: ``(("hil", "bench", "loop"), help, parser)``."""
    found = [(path, "", parser)]
    for name, help_text, sub in _subparsers(parser):
        nested = walk_cli(sub, (*path, name))
        nested[0] = (nested[0][0], help_text, nested[0][2])
        found += nested
    return found


def _option_help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    if not action.help or action.help == argparse.SUPPRESS:
        return ""
    return parser._get_formatter()._expand_help(action)


def _default(action: argparse.Action) -> str:
    if isinstance(
        action,
        argparse._StoreTrueAction
        | argparse._StoreFalseAction
        | argparse._HelpAction
        | argparse._VersionAction
        | argparse._CountAction,
    ):
        return ""
    d = action.default
    if d is None or d == argparse.SUPPRESS or d == []:
        return ""
    return code(d)


def _option_name(action: argparse.Action) -> str:
    if not action.option_strings:
        return code(action.metavar or action.dest)
    names = ", ".join(action.option_strings)
    if action.nargs == 0:
        return code(names)
    metavar = action.metavar or (action.dest.upper() if action.dest else "")
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    if action.choices and not action.metavar:
        metavar = "{" + ",".join(str(c) for c in action.choices) + "}"
    suffix = {"?": f" [{metavar}]", "*": f" [{metavar} ...]", "+": f" {metavar} [...]"}.get(
        action.nargs, f" {metavar}"
    )
    return code(names + suffix)


def _prose(parser: argparse.ArgumentParser, text: str) -> str:
    """A description or epilog: as written when the parser keeps its line breaks."""
    if issubclass(parser.formatter_class, argparse.RawDescriptionHelpFormatter):
        return "```text\n" + textwrap.dedent(text).strip("\n") + "\n```\n\n"
    return f"{esc(text)}\n\n"


def cli_page() -> str:
    from rt_controller.cli import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps usage to the terminal: the page must not

    root = build_parser()
    parsers = walk_cli(root)
    md = [
        HEADER.format(source="rt_controller.cli.build_parser()"),
        "# CLI reference\n\n",
        "One console script, `hil`. Every subcommand and option below is read from the argparse ",
        "parsers the command itself uses; `hil COMMAND --help` prints the same text.\n\n",
        "| command | what it does |\n|---|---|\n",
    ]
    for path, help_text, _ in parsers[1:]:
        name = " ".join(path)
        md.append(f"| [{code(name)}](#{slug(name)}) | {esc(help_text)} |\n")
    md.append("\n")
    for path, help_text, parser in parsers:
        name = " ".join(path)
        md.append(heading(2, name))
        if help_text:
            md.append(f"{esc(help_text)}\n\n")
        if parser.description:
            md.append(_prose(parser, parser.description))
        usage = parser.format_usage().strip().removeprefix("usage: ")
        md.append(f"```text\n{usage}\n```\n\n")
        rows = []
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                continue
            rows.append(
                f"| {_option_name(action)} | {_default(action)} "
                f"| {esc(_option_help(parser, action))} |\n"
            )
        if rows:
            md.append("| option | default | meaning |\n|---|---|---|\n")
            md += rows
            md.append("\n")
        if parser.epilog:
            md.append(_prose(parser, parser.epilog))
    return "".join(md).rstrip() + "\n"
