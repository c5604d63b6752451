"""The engines of a batch: the thread settings reach the worker processes of the pool and of a
Dask LocalCluster, each refine gets the cores over the workers, and the tasks start in the
order the batch gives them (the largest workspaces first)."""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass
from types import SimpleNamespace

import pytest

from colmap_citymodel.batch import engine as engine_module
from colmap_citymodel.batch import run as batch_run
from colmap_citymodel.batch.engine import run_dask, run_local
from colmap_citymodel.batch.task import THREAD_VARIABLES, limit_threads
from colmap_citymodel.citymodel import tiles


@dataclass
class Probe:
    """A stand-in task: a name, the threads it is given and how long it works."""

    name: str
    threads: int | None = None
    seconds: float = 0.0


def probe_threads(task: Probe) -> dict:
    """What a refine in this worker would run with: the thread variables the worker process
    started with (its libraries size their pools by them), then Open3D's limit once the task
    has set its threads."""
    import open3d

    started_with = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    if task.threads:
        limit_threads(task.threads)
    return {"workspace": task.name, "status": "done", "environment": started_with,
            "open3d": open3d.utility.get_max_threads(), "pid": os.getpid(),
            "malloc_trim": os.environ.get("MALLOC_TRIM_THRESHOLD_")}


def probe_order(task: Probe) -> dict:
    started = time.time()
    time.sleep(task.seconds)
    return {"workspace": task.name, "status": "done", "started": started, "pid": os.getpid()}


@pytest.mark.parametrize("threads", [1, 2])
def test_the_pool_workers_start_with_the_threads_of_a_task(threads):
    tasks = [Probe(f"w{k}", threads) for k in range(3)]
    rows = [row for _, row in run_local(probe_threads, tasks, workers=2, threads=threads)]
    assert sorted(r["workspace"] for r in rows) == ["w0", "w1", "w2"]
    for row in rows:
        assert row["environment"] == {name: str(threads) for name in THREAD_VARIABLES}
        assert row["open3d"] == threads


def test_the_dask_workers_start_with_the_threads_of_a_task():
    """Two threads, not the one thread per variable a Dask nanny sets by itself, and glibc's
    memory trimming as in the pool, not the nanny's."""
    before = dict(os.environ)
    tasks = [Probe(f"w{k}", 2) for k in range(2)]
    rows = [row for _, row in run_dask(probe_threads, tasks, workers=2, scheduler="local",
                                       threads=2)]
    assert len(rows) == 2
    for row in rows:
        assert row["environment"] == {name: "2" for name in THREAD_VARIABLES}
        assert row["open3d"] == 2
        assert row["malloc_trim"] == before.get("MALLOC_TRIM_THRESHOLD_")
    assert dict(os.environ) == before  # the nannies left the batch's environment alone


def test_refines_share_the_cores(monkeypatch):
    monkeypatch.setattr(batch_run, "default_workers", lambda: 8)
    assert batch_run.task_threads(1, None) == 8
    assert batch_run.task_threads(2, None) == 4
    assert batch_run.task_threads(3, "local") == 2
    assert batch_run.task_threads(16, None) == 1
    assert batch_run.task_threads(2, "tcp://scheduler:8786") == 1


@pytest.mark.parametrize("engine", ["pool", "dask"])
def test_one_worker_starts_the_tasks_in_the_order_given(engine):
    """The batch hands the tasks over largest first; one worker must start them in that
    order (Dask: also when the later tasks are submitted while the first runs)."""
    tasks = [Probe(f"w{k}", seconds=0.3 if k == 0 else 0.05) for k in range(6)]
    if engine == "pool":
        rows = [row for _, row in run_local(probe_order, tasks, workers=1)]
    else:
        rows = [row for _, row in run_dask(probe_order, tasks, workers=1, scheduler="local")]
    started = [r["workspace"] for r in sorted(rows, key=lambda r: r["started"])]
    assert started == [t.name for t in tasks]
    assert len({r["pid"] for r in rows}) == 1  # one process took them all, one after the other


def test_two_workers_keep_no_task_waiting_behind_a_long_one():
    """One long task first, then short ones on a Dask LocalCluster of two: the second worker
    runs every short task while the first is busy (none waits behind the long one)."""
    tasks = [Probe("long", seconds=6.0)] + [Probe(f"short{k}", seconds=0.1) for k in range(5)]
    rows = {row["workspace"]: row for _, row in run_dask(probe_order, tasks, workers=2,
                                                          scheduler="local")}
    long_row = rows.pop("long")
    assert [name for name, r in rows.items() if r["pid"] == long_row["pid"]] == []


def fake_workspace(directory, image_bytes: int) -> None:
    """A workspace whose images.bin has `image_bytes` bytes (its observations), GNSS in
    gnss.txt."""
    model = directory / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.bin").write_bytes(struct.pack("<Q", 1))
    (model / "images.bin").write_bytes(struct.pack("<Q", 30) + b"\0" * image_bytes)
    (directory / "gnss.txt").write_text("a.jpg 1 2 3\n")


@pytest.mark.parametrize(("workers", "threads", "expected"), [(1, None, 2), (2, None, 1),
                                                             (2, 3, 3)])
def test_the_batch_hands_the_largest_workspaces_first_to_the_engine(tmp_path, monkeypatch,
                                                                    workers, threads,
                                                                    expected):
    for name, size in {"a_small": 1_000, "b_large": 90_000, "c_tiny": 10,
                       "d_medium": 20_000}.items():
        fake_workspace(tmp_path / "flights" / name, size)
    (tmp_path / "tiles").mkdir()
    monkeypatch.setattr(batch_run, "default_workers", lambda: 2)
    monkeypatch.setattr(tiles, "build_tile_index",
                        lambda *a, **k: SimpleNamespace(tiles=[], errors=[]))
    handed = {}

    def engine(fn, tasks, workers, threads=None):
        handed.update(names=[t.name for t in tasks], task_threads={t.threads for t in tasks},
                      workers=workers, threads=threads)
        yield from ()

    monkeypatch.setattr(engine_module, "run_local", engine)
    rows = batch_run.main(tmp_path / "flights", tmp_path / "tiles", tmp_path / "out",
                          workers=workers, threads=threads, gnss_crs="EPSG:25832",
                          progress=False)
    assert handed == {"names": ["b_large", "d_medium", "a_small", "c_tiny"],
                      "task_threads": {expected}, "workers": workers, "threads": expected}
    # the summary keeps the workspaces by name
    assert [r["workspace"] for r in rows] == ["a_small", "b_large", "c_tiny", "d_medium"]
