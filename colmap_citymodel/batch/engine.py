"""Where the tasks run: a local process pool, or a Dask cluster.

Both take the same task function and task records, start the tasks in the order given (the
batch puts the largest workspaces first, so that no core idles at the end behind one long
refine) and yield `(task, row)` as tasks finish.

- `run_local`: `concurrent.futures.ProcessPoolExecutor` with the spawn start method (pycolmap,
  Open3D and Ceres hold threads and state that fork does not copy safely). Its worker
  processes live for the whole batch and take one task after the other, so each imports the
  libraries once. They start with the thread variables set to `threads` (before they import
  anything), and ignore Ctrl-C while idle; a running task is interrupted by Ctrl-C, so its
  output directory is never renamed into place. A worker that dies (a crash in native code,
  the OOM killer) breaks the pool: its tasks are run once more in a new pool, and reported as
  failed if that breaks again.
- `run_dask`: `dask.distributed`; `scheduler="local"` starts a LocalCluster of `workers`
  processes with one task slot each, whose workers start with the thread variables set to
  `threads`, without the statistical profiler (it samples the running task's stack 100
  times a second for a dashboard the LocalCluster does not open) and with glibc's default
  memory trimming (see LOCAL_CLUSTER_CONFIG). Any other value is the
  address of a running scheduler (`tcp://host:8786`). Every worker must see the workspaces,
  the city model and the output directory under the same paths, and the scheduler as well as
  the workers must import colmap_citymodel (Dask unpickles the tasks on the scheduler too).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from .task import THREAD_VARIABLES

logger = logging.getLogger(__name__)

#: How often a task whose worker died is started again.
RETRIES_AFTER_CRASH = 1


def thread_variables(threads: int | None) -> dict[str, str]:
    """The environment that holds the numeric libraries of a new worker to `threads`."""
    return {name: str(threads) for name in THREAD_VARIABLES} if threads else {}


@contextlib.contextmanager
def thread_environment(threads: int | None):
    """`threads` threads per numeric library in the environment that new workers inherit
    (None: the environment as it is); afterwards the whole environment is as before (a Dask
    nanny writes its variables into the environment of the process that starts it)."""
    saved = dict(os.environ)
    os.environ.update(thread_variables(threads))
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def _ignore_interrupts() -> None:
    """Pool initializer: an idle worker ignores Ctrl-C (the parent shuts the pool down)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _interruptible(fn: Callable, task):
    """Run `fn(task)` with Ctrl-C raising KeyboardInterrupt inside it."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return fn(task)
    finally:
        signal.signal(signal.SIGINT, previous)


def _crash_row(task, error: str) -> dict:
    return {"workspace": task.name, "status": "error", "error": error}


def run_local(fn: Callable, tasks: list, workers: int, threads: int | None = None
              ) -> Iterator[tuple[object, dict]]:
    """Run `fn` on every task, in their order, in a pool of `workers` spawned processes
    started with `threads` threads per numeric library."""
    context = multiprocessing.get_context("spawn")
    attempts = {id(t): 0 for t in tasks}
    pending = list(tasks)
    while pending:
        with thread_environment(threads):
            pool = ProcessPoolExecutor(max_workers=min(workers, len(pending)),
                                       mp_context=context, initializer=_ignore_interrupts)
            futures = {pool.submit(_interruptible, fn, t): t for t in pending}
        pending = []
        try:
            waiting = set(futures)
            while waiting:
                done, waiting = wait(waiting, return_when=FIRST_COMPLETED)
                for future in done:
                    task = futures[future]
                    try:
                        row = future.result()
                    except BrokenProcessPool:
                        attempts[id(task)] += 1
                        if attempts[id(task)] <= RETRIES_AFTER_CRASH:
                            pending.append(task)
                            continue
                        row = _crash_row(task, "the worker process died (a crash in native "
                                               "code or out of memory); see its log")
                    except Exception as error:  # the task could not be sent or returned
                        row = _crash_row(task, f"{type(error).__name__}: {error}")
                    yield task, row
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        if pending:
            logger.warning("a worker process died; %d unfinished workspace(s) start again in "
                           "a new pool", len(pending))


#: Dask settings of a LocalCluster: no statistical profiling of the running tasks (there is
#: no dashboard to show it), and glibc's own memory trimming in the workers instead of the
#: nanny's MALLOC_TRIM_THRESHOLD_=65536, which returns every freed block above 64 KiB to the
#: system at once and so multiplies a refine's page faults.
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}


def run_dask(fn: Callable, tasks: list, workers: int, scheduler: str,
             threads: int | None = None) -> Iterator[tuple[object, dict]]:
    """Run `fn` on every task on a Dask cluster (`scheduler`: "local" or an address), the
    first tasks first; a LocalCluster's workers start with `threads` threads per numeric
    library."""
    try:
        import dask
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as error:  # pragma: no cover - a dependency of the package
        raise ImportError("the Dask engine needs dask.distributed: pip install "
                          "'dask[distributed]'") from error
    cluster = None
    if scheduler == "local":
        with dask.config.set(LOCAL_CLUSTER_CONFIG), thread_environment(threads):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR,
                                   env=thread_variables(threads))
        client = Client(cluster)
    else:
        client = Client(scheduler)
    futures: dict = {}
    try:
        futures = {client.submit(fn, t, key=f"refine-{k}-{t.name.replace('/', '-')}",
                                 pure=False, priority=len(tasks) - k): t
                   for k, t in enumerate(tasks)}
        for future in as_completed(futures):
            task = futures[future]
            try:
                row = future.result()
            except Exception as error:  # KilledWorker, a lost connection, ...
                row = _crash_row(task, f"{type(error).__name__}: {error}")
            yield task, row
    finally:
        with contextlib.suppress(Exception):
            client.cancel(list(futures))
        client.close()
        if cluster is not None:
            cluster.close()
