"""One workspace's refine as a task for a worker process (a local pool or a Dask worker).

The task gets paths only: it indexes the city model (from the cache the batch filled), reads
the workspace's GNSS to find the tiles within `workflow.GNSS_READ_MARGIN` of it, and runs
`workflow.main()` on those tiles, which writes `OUT/<workspace>/` atomically. Everything the
refine logs or prints goes to `OUT/<workspace>.log`, a traceback too. It returns one row of
the summary (a plain dict); a domain error (`CityModelError`) or any other exception becomes
that row's `error` and never escapes, so one workspace cannot stop the others.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import CityModelError, CRSError, NoOverlapError
from .summary import read_report_row

logger = logging.getLogger(__name__)

#: The variables the numeric libraries (OpenMP, OpenBLAS, MKL, ...) size their thread pools
#: by when they are loaded; a worker process gets them before it imports anything.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


@dataclass
class Task:
    """Everything one workspace's refine needs, as paths and plain values."""

    name: str
    model: str  # sparse/<n>
    output: str  # OUT/<name>
    log: str  # OUT/<name>.log
    citymodel: list[str]  # files and directories of tiles
    cache_dir: str  # where the tile index is cached when the data directory is read-only
    database: str | None = None
    gnss: str | None = None
    exif: str | None = None
    gnss_crs: str | None = None
    replace: bool = False  # an earlier result at `output` is replaced (--force)
    threads: int | None = None  # threads of this refine (None: the libraries' defaults)
    refine: dict = field(default_factory=dict)  # keyword arguments of workflow.main()


def select_tiles(task: Task) -> list[Path]:
    """The tiles within GNSS_READ_MARGIN of the workspace's GNSS positions, in the CRS of the
    tiles (or --target_crs). Tiles of several CRSs near one block are an error (pass
    --target_crs to read them together)."""
    from ..block.gnss import read_gnss
    from ..citymodel.crs import user_crs
    from ..citymodel.tiles import build_tile_index
    from ..workflow import GNSS_READ_MARGIN

    index = build_tile_index(task.citymodel, cache_dir=task.cache_dir)
    model_crs, target_crs = task.refine.get("model_crs"), task.refine.get("target_crs")
    assumed = user_crs(model_crs) if model_crs else None
    if target_crs:
        candidates = [user_crs(target_crs)]
    else:
        candidates = [crs for crs in index.crs_groups(assumed) if crs.is_projected]
        if not candidates:
            raise CRSError("no tile of the city model names a projected CRS; pass --crs for "
                           "tiles that name none, --target_crs for geographic ones")
    found = []
    for crs in candidates:
        gnss = read_gnss(database=task.database, gnss=task.gnss, gnss_crs=task.gnss_crs,
                         exif=task.exif, target_crs=crs)
        lo = gnss.positions.min(0)[:2] - GNSS_READ_MARGIN
        hi = gnss.positions.max(0)[:2] + GNSS_READ_MARGIN
        tiles = index.select([lo, hi], crs, assumed=assumed)
        if tiles:
            found.append((crs, tiles))
    if not found:
        raise NoOverlapError(
            f"no tile of the city model lies within {GNSS_READ_MARGIN:.0f} m of the GNSS "
            f"positions (tiles in {', '.join(c.label for c in candidates)}); check the GNSS "
            "CRS and the tiles", task.model)
    if len(found) > 1:
        raise CRSError("tiles in more than one CRS lie near the GNSS positions ("
                       + ", ".join(f"{c.label}: {len(t)}" for c, t in found)
                       + "); pass --target_crs to read them in one")
    return [t.path for t in found[0][1]]


def limit_threads(threads: int) -> None:
    """At most `threads` threads in this process: the thread variables (for the libraries
    loaded from now on) and Open3D's TBB pool, which reads no variable. Ceres gets its
    threads per solve (workflow.main's num_threads)."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    import open3d

    open3d.utility.set_max_threads(threads)


@contextlib.contextmanager
def captured(log_path: Path):
    """Route the package's log records, stdout and stderr into `log_path` (overwritten)."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    package = logging.getLogger("colmap_citymodel")
    with open(log_path, "w", buffering=1) as stream:
        handler = logging.StreamHandler(stream)
        handler.setFormatter(logging.Formatter(
            "[%(asctime)s %(name)s %(levelname)s] %(message)s", "%H:%M:%S"))
        saved, level = package.handlers[:], package.level
        package.handlers = [handler]
        if package.level > logging.INFO or package.level == logging.NOTSET:
            package.setLevel(logging.INFO)
        try:
            with contextlib.redirect_stdout(stream), contextlib.redirect_stderr(stream):
                yield stream
        finally:
            package.handlers = saved
            package.setLevel(level)


def _swap_in(staging: Path, output: Path) -> None:
    """Replace `output` by the finished `staging` directory (never a half-written one)."""
    old = output.parent / f".{output.name}.old-{os.getpid()}"
    if output.exists():
        os.replace(output, old)
    os.replace(staging, output)
    shutil.rmtree(old, ignore_errors=True)


def refine_workspace(task: Task) -> dict:
    """Refine one workspace; the summary row (see summary.COLUMNS). Never raises for a failed
    refine (only KeyboardInterrupt passes)."""
    started = time.perf_counter()
    row: dict = {"workspace": task.name, "status": "error",
                 "gnss": ("database" if task.database else "gnss.txt" if task.gnss
                          else "exif" if task.exif else None)}
    if task.threads:
        limit_threads(task.threads)
    output = Path(task.output)
    with captured(Path(task.log)) as log:
        try:
            tiles = select_tiles(task)
            row["tiles"] = len(tiles)
            row["tile_files"] = [p.name for p in tiles]
            logger.info("%s: %d tile(s) near its GNSS: %s", task.name, len(tiles),
                        ", ".join(p.name for p in tiles))
            from ..workflow import main as refine_main

            target = output
            if task.replace and output.exists():
                target = output.parent / f".{output.name}.rerun-{os.getpid()}"
                shutil.rmtree(target, ignore_errors=True)
            refine_main(task.model, [str(p) for p in tiles], target, database=task.database,
                        gnss=task.gnss, gnss_crs=task.gnss_crs, exif=task.exif,
                        progress=False, num_threads=task.threads,
                        **task.refine)
            if target != output:
                _swap_in(target, output)
            row.update(read_report_row(output / "report.json"))
            row["status"] = "done"
        except KeyboardInterrupt:
            print(f"{task.name}: interrupted", file=log)
            raise
        except CityModelError as error:
            row["error"] = str(error)
            print(f"error: {error}", file=log)
        except Exception as error:  # anything else: its type and the traceback in the log
            row["error"] = f"{type(error).__name__}: {error}"
            traceback.print_exc(file=log)
        row["seconds"] = round(time.perf_counter() - started, 2)
        print(f"{task.name}: {row['status']} in {row['seconds']:.1f} s", file=log)
    return row
