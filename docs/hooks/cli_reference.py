"""MkDocs hook: the CLI reference page, written from the argparse parsers at build time.

`docs/reference/cli.md` holds the line `<!-- cli-reference -->`; this hook replaces it with one
section per subcommand of `colmap_citymodel.cli.build_parser()`: its help, its usage line and
one table of options per argument group (flags, default, help), then its epilog. The page
therefore says what `colmap-citymodel <command> --help` says, in the version that is built.
"""

from __future__ import annotations

import argparse
import html
import os

MARKER = "<!-- cli-reference -->"
PAGE = "reference/cli.md"
WIDTH = "100"  # usage lines wrapped as on a 100-column terminal, whatever builds the docs


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _flags(action: argparse.Action) -> str:
    if action.option_strings:
        names = ", ".join(f"`{name}`" for name in action.option_strings)
    else:
        names = f"`{action.metavar or action.dest}`"
    if action.nargs == 0:
        return names
    if action.choices is not None and not action.option_strings:
        return names
    if action.choices is not None:
        return f"{names} `{{{','.join(str(c) for c in action.choices)}}}`"
    metavar = action.metavar or action.dest.upper()
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    if action.nargs in ("+", "*"):
        metavar = f"{metavar} ..."
    if "|" in metavar:  # a code span cannot hold a pipe inside a table cell
        return f"{names} <code>{html.escape(metavar).replace('|', '&#124;')}</code>"
    return f"{names} `{metavar}`"


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    if not action.option_strings:
        return "positional" if action.nargs not in ("?", "*") else ""
    default = action.default
    if default is None or default is argparse.SUPPRESS or action.nargs == 0:
        return ""
    if isinstance(default, (list, tuple)):
        default = " ".join(str(value) for value in default)
    return f"`{default}`"


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    if not action.help or action.help is argparse.SUPPRESS:
        return ""
    return _cell(parser._get_formatter()._expand_help(action))


def _section(name: str, parser: argparse.ArgumentParser, summary: str) -> list[str]:
    lines = [f"## {name}", ""]
    if summary:
        lines += [summary[0].upper() + summary[1:] + ".", ""]
    if parser.description:
        lines += [parser.description, ""]
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if not isinstance(a, argparse._HelpAction)]
        if not actions:
            continue
        title = group.title or "options"
        lines += [f"**{title[0].upper() + title[1:]}**", ""]
        if group.description:
            lines += [group.description, ""]
        lines += ["| option | default | description |", "|---|---|---|"]
        for action in actions:
            lines.append(f"| {_flags(action)} | {_default(action)} | {_help(parser, action)} |")
        lines.append("")
    if parser.epilog:
        lines += [parser.epilog[0].upper() + parser.epilog[1:] + ".", ""]
    return lines


def cli_reference_markdown() -> str:
    """The reference of every subcommand, in the order the parser lists them."""
    from colmap_citymodel.cli import build_parser

    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        parser = build_parser()
        sub_action = next(a for a in parser._actions
                          if isinstance(a, argparse._SubParsersAction))
        summaries = {choice.dest: choice.help or "" for choice in sub_action._choices_actions}
        lines = ["```text", parser.format_usage().strip(), "```", ""]
        lines += ["| command | what it does |", "|---|---|"]
        for name in sub_action.choices:
            lines.append(f"| [`{name}`](#{name}) | {_cell(summaries.get(name, ''))} |")
        lines.append("")
        for name, sub in sub_action.choices.items():
            lines += _section(name, sub, summaries.get(name, ""))
    finally:
        if columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = columns
    return "\n".join(lines)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"docs/{PAGE} lacks the line {MARKER} that the CLI reference replaces")
    return markdown.replace(MARKER, cli_reference_markdown())
