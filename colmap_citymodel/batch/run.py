"""`colmap-citymodel batch`: refine many COLMAP workspaces against one city model, without a
GUI, on this machine's cores or a Dask cluster.

1. find the workspaces (batch.workspaces) and index the city model's tiles once
   (citymodel.tiles: bounding box and CRS of every file, cached next to the data or under
   `OUT/.cache/`);
2. skip the workspaces finished by an earlier run (`OUT/<workspace>/report.json` exists)
   unless `force`;
3. run one task per workspace (batch.task) on a local process pool or a Dask cluster
   (batch.engine), the largest workspaces first (most image observations: the longest
   refines, so that the last ones to finish are short), each on the cores over the workers
   (`task_threads`): each reads the tiles near its GNSS and writes `OUT/<workspace>/`
   atomically and `OUT/<workspace>.log`;
4. after every finished workspace, rewrite `OUT/summary.csv`, `summary.json` and
   `summary.html` (batch.summary); a status line per workspace and a progress bar on the
   console, the summary table at the end.

A failed workspace (bad input, no tile near its GNSS, an exception) is a row with its error;
the others go on. Ctrl-C stops the running refines before their output is renamed into place
and leaves a summary of what finished.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

from ..errors import InputError
from .summary import counts, read_report_row, read_summary, status_line, table, write_summary
from .task import Task
from .workspaces import find_workspaces

logger = logging.getLogger(__name__)

#: Keyword arguments of workflow.main() that a batch passes to every workspace's refine.
REFINE_OPTIONS = ("preset", "options_file", "assignment", "lod", "model_crs", "target_crs",
                  "output_type", "output_frame", "precision", "sigma_generalisation",
                  "variance_components", "gnss_height_offset", "gnss_bias", "lever_arm",
                  "write_model")


def default_workers() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def task_threads(workers: int, scheduler: str | None) -> int:
    """Threads of each refine: this machine's cores shared by the local workers, so that
    they do not oversubscribe them; one on a remote Dask cluster (one task per worker
    thread)."""
    if scheduler not in (None, "local"):
        return 1
    return max(1, default_workers() // workers)


def workspace_size(model: Path) -> int:
    """Bytes of the model's images file: its image observations, which the refine's time
    grows with."""
    for name in ("images.bin", "images.txt"):
        try:
            return (model / name).stat().st_size
        except OSError:
            pass
    return 0


def _remove_stale(output: Path, name: str) -> None:
    """What an interrupted or killed refine of `name` can leave behind: its temporary
    directories, and an empty output directory (its check that the output is free)."""
    target = output / name
    if not target.parent.is_dir():
        return
    for stale in target.parent.glob(f".{target.name}.*"):
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)
    if target.is_dir() and not any(target.iterdir()):
        target.rmdir()


def main(workspaces, citymodel, output_path, *, workers: int | None = None,
         threads: int | None = None, scheduler: str | None = None, force: bool = False,
         gnss_crs: str | None = None, progress: bool = True, **refine) -> list[dict]:
    """Refine every workspace named by `workspaces` into `output_path/<workspace>/`; the
    summary rows (also written to `output_path/summary.*`). `workers`: processes of the local
    pool or of a Dask LocalCluster (default: the cores); `threads`: threads of each refine
    (default: `task_threads`, the cores over the workers); `scheduler`: None (local pool),
    "local" (a Dask LocalCluster) or a Dask scheduler's address; `refine`: the options of
    REFINE_OPTIONS, as workflow.main() takes them."""
    from ..citymodel.tiles import build_tile_index
    from ..options import RefineOptions
    from .engine import run_dask, run_local
    from .task import refine_workspace

    unknown = set(refine) - set(REFINE_OPTIONS)
    if unknown:
        raise TypeError(f"unknown refine option(s): {', '.join(sorted(unknown))}")
    refine = {k: v for k, v in refine.items() if v is not None}
    if refine.get("options_file"):  # a bad options file fails once, not once per workspace
        RefineOptions.from_toml(refine["options_file"], refine.get("preset", "generalised"))
        refine["options_file"] = str(Path(refine["options_file"]).resolve())
    workers = int(workers) if workers else default_workers()
    if workers < 1:
        raise InputError(f"--workers must be at least 1, not {workers}")
    if threads is not None and int(threads) < 1:
        raise InputError(f"--threads must be at least 1, not {threads}")
    output = Path(output_path).resolve()
    if output.exists() and not output.is_dir():
        raise InputError("output path is a file; give a directory", output)
    output.mkdir(parents=True, exist_ok=True)
    citymodel = [str(Path(p).resolve()) for p in
                 ([citymodel] if isinstance(citymodel, (str, Path)) else citymodel)]

    found = find_workspaces(workspaces)
    cache_dir = output / ".cache"
    index = build_tile_index(citymodel, cache_dir=cache_dir)  # the one pass over the tiles
    for tile in index.errors:
        logger.warning("%s: not indexed, never read: %s", tile.path, tile.error)
    if not refine.get("model_crs"):
        nameless = [t for t in index.tiles if not t.error and not t.srs_name]
        if nameless:
            logger.warning("%d tile(s) name no CRS and are not used (give --crs): %s",
                           len(nameless), ", ".join(t.path.name for t in nameless[:5]))

    previous = read_summary(output)
    rows: dict[str, dict] = {}
    tasks: list[Task] = []
    threads = int(threads) if threads else task_threads(workers, scheduler)
    for ws in found:
        target = output / ws.name
        row = {"workspace": ws.name, "gnss": ws.gnss_source}
        _remove_stale(output, ws.name)
        if not force and (target / "report.json").is_file():
            before = previous.get(ws.name, {})
            row = ({**before} if before.get("status") in ("done", "skipped")
                   else {**row, **read_report_row(target / "report.json")})
            row["status"] = "skipped"
        elif ws.problem or (ws.gnss and not gnss_crs):
            row.update(status="error", error=f"{ws.path}: " + (
                ws.problem or "gnss.txt needs --gnss_crs (the CRS of its coordinates, e.g. "
                              "EPSG:25832 or EPSG:4979)"))
        else:
            row["status"] = "not run"
            tasks.append(Task(
                name=ws.name, model=str(ws.model), output=str(target),
                log=str(output / f"{ws.name}.log"), citymodel=citymodel,
                cache_dir=str(cache_dir), database=str(ws.database) if ws.database else None,
                gnss=str(ws.gnss) if ws.gnss else None, exif=str(ws.exif) if ws.exif else None,
                gnss_crs=gnss_crs, replace=force, threads=threads, refine=refine))
        rows[ws.name] = row

    tasks.sort(key=lambda t: -workspace_size(Path(t.model)))  # the longest refines first
    engine = ("a process pool" if scheduler is None else "a Dask LocalCluster"
              if scheduler == "local" else f"the Dask scheduler at {scheduler}")
    print(f"batch: {len(found)} workspace(s), {len(tasks)} to refine on {engine}"
          + (f" of {workers} worker(s)" if scheduler in (None, "local") else "")
          + f", {threads} thread(s) per workspace; {len(index.tiles)} city model tile(s); "
          f"output {output}")
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), unit="workspace", desc="batch", disable=not progress)
    say = bar.write if progress else print
    for row in rows.values():
        if row["status"] != "not run":
            say(status_line(row))
    write_summary(output, list(rows.values()))
    try:
        finished = (run_local(refine_workspace, tasks, workers, threads) if scheduler is None
                    else run_dask(refine_workspace, tasks, workers, scheduler, threads))
        try:
            for task, row in finished if tasks else ():
                rows[task.name] = {**rows[task.name], **row}
                say(status_line(rows[task.name]))
                bar.update(1)
                write_summary(output, list(rows.values()))
        finally:
            finished.close()  # shuts the pool or cluster down, also on Ctrl-C
            if scheduler in (None, "local"):  # no worker of ours writes any more
                for task in tasks:
                    _remove_stale(output, task.name)
            for task in tasks:
                # A refine that completed its output just as Ctrl-C came: its result never
                # reached this process, but its output is whole (written atomically).
                report = Path(task.output) / "report.json"
                if rows[task.name]["status"] == "not run" and report.is_file():
                    rows[task.name] = {**rows[task.name], **read_report_row(report),
                                       "status": "done"}
    finally:
        bar.close()
        write_summary(output, list(rows.values()))
    result = list(rows.values())
    print()
    print(table(result))
    print()
    print(f"{counts(result)}; summary: {output / 'summary.csv'}, summary.json, summary.html")
    return result
