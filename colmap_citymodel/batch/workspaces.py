"""Finding the COLMAP workspaces of a batch and what each gives refine.

A workspace is a directory with a COLMAP model in `sparse/<n>/` (or in `sparse/` itself) and
GNSS from one of, in this order: `database.db` with pose priors that have a position (what
`colmap-citymodel simulate` and COLMAP's feature extractor on geotagged images write),
`gnss.txt` (`image_name X Y Z [sX sY sZ]`, its CRS given once for the batch by `--gnss_crs`),
or `images/` whose files carry EXIF GPS. Where COLMAP split a block into several models, the
one with the most registered images is refined.

`--workspaces` names a workspace, a directory searched for workspaces (hidden directories and
the inside of a workspace are not searched), or a text file listing workspace directories one
a line (`#` comments; relative paths from the list file's directory). A workspace's name, and
the name of its output directory, is its path relative to the deepest directory common to all
workspaces of the batch.
"""

from __future__ import annotations

import os
import sqlite3
import struct
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

MODEL_FILES = ("cameras.bin", "cameras.txt")
DATABASE_NAME = "database.db"
GNSS_NAME = "gnss.txt"
IMAGES_NAME = "images"
#: Directories searched below a `--workspaces` directory.
MAX_DEPTH = 6


@dataclass
class Workspace:
    """One block to refine: its inputs, found on disk, and why it cannot be refined."""

    name: str
    path: Path
    model: Path | None = None  # sparse/<n>
    database: Path | None = None
    gnss: Path | None = None
    exif: Path | None = None
    problem: str | None = None  # set when the inputs are incomplete

    @property
    def gnss_source(self) -> str | None:
        return ("database" if self.database else "gnss.txt" if self.gnss
                else "exif" if self.exif else None)


def _is_model(directory: Path) -> bool:
    return any((directory / f).is_file() for f in MODEL_FILES)


def model_directories(workspace: Path) -> list[Path]:
    """The COLMAP models of a workspace: sparse/<n>/ (numbered first, in order), or sparse/."""
    sparse = workspace / "sparse"
    if not sparse.is_dir():
        return []
    subs = [d for d in sparse.iterdir() if d.is_dir() and _is_model(d)]
    subs.sort(key=lambda d: (not d.name.isdigit(), int(d.name) if d.name.isdigit() else 0,
                             d.name))
    if subs:
        return subs
    return [sparse] if _is_model(sparse) else []


def registered_images(model: Path) -> int:
    """Number of images in a COLMAP model, from the head of images.bin (or images.txt)."""
    binary, text = model / "images.bin", model / "images.txt"
    try:
        if binary.is_file():
            with open(binary, "rb") as f:
                head = f.read(8)
            return struct.unpack("<Q", head)[0] if len(head) == 8 else 0
        if text.is_file():
            lines = [ln for ln in text.read_text().splitlines()
                     if ln.strip() and not ln.startswith("#")]
            return len(lines) // 2
    except OSError:
        pass
    return 0


def pose_prior_count(database: Path) -> int:
    """Pose priors with a position in a COLMAP database (read-only; 0 when unreadable)."""
    try:
        connection = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
    except sqlite3.Error:
        return 0
    try:
        return int(connection.execute(
            "SELECT COUNT(*) FROM pose_priors WHERE position IS NOT NULL").fetchone()[0])
    except sqlite3.Error:
        return 0
    finally:
        connection.close()


def describe(path: Path, name: str) -> Workspace:
    """The inputs of the workspace at `path` (problems are recorded, not raised)."""
    ws = Workspace(name=name, path=path)
    if not path.is_dir():
        ws.problem = "no such directory"
        return ws
    models = model_directories(path)
    if not models:
        ws.problem = "no COLMAP model in sparse/ (sparse/0/cameras.bin ...)"
        return ws
    ws.model = max(models, key=registered_images)  # max keeps the first of equals
    database, gnss, images = path / DATABASE_NAME, path / GNSS_NAME, path / IMAGES_NAME
    if database.is_file() and pose_prior_count(database) > 0:
        ws.database = database
    elif gnss.is_file():
        ws.gnss = gnss
    elif images.is_dir():
        ws.exif = images
    else:
        ws.problem = (f"no GNSS: neither {DATABASE_NAME} with pose priors nor {GNSS_NAME} nor "
                      f"{IMAGES_NAME}/ with EXIF GPS")
    return ws


def is_workspace(path: Path) -> bool:
    return path.is_dir() and bool(model_directories(path))


def _search(root: Path) -> list[Path]:
    if is_workspace(root):
        return [root]
    found: list[Path] = []
    for directory, subdirs, _files in os.walk(root):
        here = Path(directory)
        depth = len(here.relative_to(root).parts)
        subdirs[:] = sorted(d for d in subdirs if not d.startswith("."))
        if depth >= MAX_DEPTH:
            subdirs[:] = []
            continue
        keep = []
        for d in subdirs:
            if is_workspace(here / d):
                found.append(here / d)
            else:
                keep.append(d)
        subdirs[:] = keep
    return found


def _read_list(path: Path) -> list[Path]:
    """The directories a list file names (a missing one becomes that workspace's problem)."""
    out = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            p = Path(line).expanduser()
            out.append(p if p.is_absolute() else path.parent / p)
    return out


def find_workspaces(items) -> list[Workspace]:
    """The workspaces named by `items` (directories and list files; see the module doc), in
    a stable order and with unique names."""
    if isinstance(items, (str, Path)):
        items = [items]
    paths: list[Path] = []
    for item in map(Path, items):
        if item.is_file():
            paths += _read_list(item)
        elif item.is_dir():
            found = _search(item)
            if not found:
                raise InputError("no COLMAP workspace (a directory with sparse/<n>/) found in",
                                 item)
            paths += found
        else:
            raise InputError("no such workspace directory or list file", item)
    unique: list[Path] = []
    for p in (p.resolve() for p in paths):
        if p not in unique:
            unique.append(p)
    if not unique:
        raise InputError("no workspace given")
    common = Path(os.path.commonpath([p.parent for p in unique]))
    return [describe(p, p.relative_to(common).as_posix()) for p in unique]
