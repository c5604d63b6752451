"""Output directories that appear whole or not at all, the PLY writer, and COLMAP's log sent to
a file."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import InputError


@contextmanager
def atomic_directory(output_path: str | Path):
    """Yield a temporary directory that becomes `output_path` when the block succeeds."""
    output_path = Path(output_path)
    if output_path.exists() and (not output_path.is_dir() or any(output_path.iterdir())):
        raise InputError("output path exists and is not an empty directory; give a new one",
                         output_path)
    output_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{output_path.name}.", dir=output_path.parent))
    try:
        yield tmp
        if output_path.exists():
            output_path.rmdir()
        os.replace(tmp, output_path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_point_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray,
                    scalars: dict[str, np.ndarray] | None = None) -> None:
    """Binary PLY with float64 coordinates (CRS coordinates do not fit float32) and colours."""
    scalars = scalars or {}
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
              ("blue", "u1")] + [(name, "<f4") for name in scalars]
    data = np.empty(len(xyz), dtype=fields)
    data["x"], data["y"], data["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    for name, values in scalars.items():
        data[name] = values
    ply_type = {"<f8": "double", "u1": "uchar", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}"]
    header += [f"property {ply_type[t]} {name}" for name, t in fields]
    header += ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode())
        f.write(data.tobytes())


def check_new_directory(path) -> None:
    """Raise InputError now if `path` cannot become a new output directory."""
    with atomic_directory(path):
        pass
    Path(path).rmdir()


@contextlib.contextmanager
def quiet_colmap(log_path: Path):
    """Send COLMAP's glog output (and anything else on fds 1/2) to `log_path`."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        saved = os.dup(1), os.dup(2)
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def content_lines(path: Path, what: str = "file"):
    """(line number, content) of each line of the text file `path` that holds more than a
    comment ('#' to the end of a line); unreadable: an InputError naming `what` and the file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read {what}: {error}", path) from None
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].strip()
        if content:
            yield number, content
