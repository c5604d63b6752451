"""MkDocs hook: include a Markdown file from elsewhere in the repository into a page.

A page line `<!-- include-repo-file: tests/data/README.md -->` is replaced by that file's text
(path from the repository root). Its relative links point at files beside it, outside the
site, so each becomes the link text followed by the file's repository path in code, e.g.
`[text](licenses/MIT.txt)` -> text (`tests/data/licenses/MIT.txt`). Links with a scheme or an
anchor stay as they are. A missing file fails the build.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

INCLUDE = re.compile(r"^<!-- include-repo-file: (\S+) -->$", re.MULTILINE)
LINK = re.compile(r"\[([^\]]+)\]\((?![a-z][a-z0-9+.-]*:|#)([^)\s]+)\)")


def _include(match: re.Match, root: Path) -> str:
    relative = match.group(1)
    path = root / relative
    if not path.is_file():
        raise FileNotFoundError(f"include-repo-file: {relative} does not exist")
    folder = posixpath.dirname(relative)

    def rewrite(link: re.Match) -> str:
        target = posixpath.normpath(posixpath.join(folder, link.group(2)))
        return f"{link.group(1)} (`{target}`)"

    return LINK.sub(rewrite, path.read_text(encoding="utf-8"))


def on_page_markdown(markdown: str, page, config, files) -> str:
    root = Path(config["config_file_path"]).parent
    return INCLUDE.sub(lambda m: _include(m, root), markdown)
