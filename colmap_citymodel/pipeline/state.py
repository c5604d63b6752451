"""The record of a run (`run.json` in its output directory): each step with what it did or
reused and its time, the cameras the images share, the matcher chosen and why. It is rewritten
atomically after every step, so an interrupted run leaves the steps it finished."""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError

logger = logging.getLogger(__name__)

STATE_NAME = "run.json"
#: Bump when the record's meaning changes (an older record is then not trusted for reuse).
STATE_VERSION = 1


def write_text_atomic(path: Path, text: str) -> None:
    """`text` into `path` through a temporary file in the same directory, so a reader sees
    the old file or the new one, never a part."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@dataclass
class Step:
    """One step of a run: "done" (it did its work now) or "reused" (a previous run's)."""

    name: str
    status: str = "running"
    seconds: float = 0.0
    details: dict = field(default_factory=dict)

    def todict(self) -> dict:
        return {"name": self.name, "status": self.status, "seconds": round(self.seconds, 2),
                **self.details}


@dataclass
class RunState:
    """`run.json`: the steps of this run, and what earlier runs left for it to reuse
    (`cameras`: the database's camera id of each camera group)."""

    path: Path
    steps: list[Step] = field(default_factory=list)
    cameras: dict[str, int] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @classmethod
    def open(cls, output_path: Path) -> RunState:
        """The state of the run directory `output_path` (created when it is new). InputError
        for a directory that holds other files and no run record."""
        output_path = Path(output_path)
        path = output_path / STATE_NAME
        if output_path.exists() and not output_path.is_dir():
            raise InputError("output path exists and is not a directory", output_path)
        if output_path.is_dir() and not path.exists() and any(output_path.iterdir()):
            raise InputError(f"output path exists and holds no {STATE_NAME} of an earlier run: "
                             "give a new directory, or the one a run wrote", output_path)
        output_path.mkdir(parents=True, exist_ok=True)
        state = cls(path)
        if path.exists():
            try:
                doc = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as error:
                raise InputError(f"unreadable run record: {error}", path) from None
            if doc.get("version") == STATE_VERSION:
                state.cameras = {str(k): int(v) for k, v in doc.get("cameras", {}).items()}
        return state

    @contextmanager
    def step(self, name: str):
        """Time the block as step `name`, log its start and end, record it."""
        step = Step(name)
        self.steps.append(step)
        logger.info("step %s ...", name)
        start = time.perf_counter()
        try:
            yield step
        except BaseException:
            step.status = "failed"
            raise
        finally:
            step.seconds = time.perf_counter() - start
            if step.status == "running":
                step.status = "done"
            logger.info("step %s: %s in %.1f s%s", name, step.status, step.seconds,
                        f" ({step.details['summary']})" if "summary" in step.details else "")
            self.save()

    def save(self) -> None:
        doc = {"version": STATE_VERSION, **self.info, "cameras": self.cameras,
               "steps": [s.todict() for s in self.steps]}
        write_text_atomic(self.path, json.dumps(doc, indent=2, default=_plain))

    def table(self) -> str:
        """The steps as printed at the end: name, status, seconds."""
        lines = [f"  {s.name:<10} {s.status:<7} {s.seconds:8.1f} s  {s.details.get('summary', '')}"
                 for s in self.steps]
        total = sum(s.seconds for s in self.steps)
        return "\n".join(["steps:"] + lines + [f"  {'total':<18} {total:8.1f} s"])


def _plain(value):
    """JSON for numpy scalars and arrays, paths and tuples in the record."""
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)
