"""MkDocs hook: option tables written from the package's dataclasses at build time.

`docs/reference/options.md` holds the line `<!-- options-reference -->`; this hook replaces it
with one section per field of `RefineOptions` (`[assignment]`, `[adjustment]`, ...): the
section's class docstring and a table of its options with their defaults (from the
dataclasses) and their attribute docstrings (read from the module's source, where Python keeps
them). The page therefore lists exactly the keys an options file may set.
`docs/verdict.md` holds `<!-- quality-thresholds -->`, replaced by the table of the quality
gate's limits (`precision.quality.QualityThresholds`) made the same way.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect

MARKER = "<!-- options-reference -->"
PAGE = "reference/options.md"
QUALITY_MARKER = "<!-- quality-thresholds -->"
QUALITY_PAGE = "verdict.md"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _attribute_docstrings(source: str) -> dict[str, dict[str, str]]:
    """{class name: {field name: docstring}} for the string literal after each annotated field."""
    docs: dict[str, dict[str, str]] = {}
    for node in ast.parse(source).body:
        if not isinstance(node, ast.ClassDef):
            continue
        fields: dict[str, str] = {}
        body = node.body
        for statement, following in zip(body, body[1:]):
            if (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)
                    and isinstance(following, ast.Expr)
                    and isinstance(following.value, ast.Constant)
                    and isinstance(following.value.value, str)):
                fields[statement.target.id] = inspect.cleandoc(following.value.value)
        docs[node.name] = fields
    return docs


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "required"
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (tuple, list)):
        return "`[" + ", ".join(f'"{v}"' if isinstance(v, str) else str(v) for v in value) + "]`"
    if value is None:
        return "unset"
    return f"`{value}`"


def _table(cls, docs: dict[str, dict[str, str]], head: str = "option") -> list[str]:
    lines = [f"| {head} | default | description |", "|---|---|---|"]
    for f in dataclasses.fields(cls):
        text = docs.get(cls.__name__, {}).get(f.name, "")
        lines.append(f"| `{f.name}` | {_default(f)} | {_cell(text)} |")
    return lines + [""]


def options_reference_markdown() -> str:
    from colmap_citymodel import options as module

    docs = _attribute_docstrings(inspect.getsource(module))
    lines: list[str] = []
    for section in dataclasses.fields(module.RefineOptions):
        cls = section.default_factory
        lines += [f"## `[{section.name}]`", ""]
        if cls.__doc__:
            lines += [inspect.cleandoc(cls.__doc__), ""]
        lines += _table(cls, docs)
    return "\n".join(lines)


def quality_thresholds_markdown() -> str:
    from colmap_citymodel.precision import quality as module

    docs = _attribute_docstrings(inspect.getsource(module))
    return "\n".join(_table(module.QualityThresholds, docs, head="limit"))


def on_page_markdown(markdown: str, page, config, files) -> str:
    for page_uri, marker, make in ((PAGE, MARKER, options_reference_markdown),
                                   (QUALITY_PAGE, QUALITY_MARKER, quality_thresholds_markdown)):
        if page.file.src_uri != page_uri:
            continue
        if marker not in markdown:
            raise ValueError(f"docs/{page_uri} lacks the line {marker} that this hook replaces")
        markdown = markdown.replace(marker, make())
    return markdown
