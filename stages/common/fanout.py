"""Fan-out of independent jobs (one scene each) over a local process pool or a Dask cluster.

Jobs must not depend on which worker runs them or in which order (each derives its own seed from
its job), so that every engine writes the same files. `fn(shared, job)` must be a module-level
function; `shared` is sent to each worker once (process pool) or with each task (Dask).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from typing import Any, TypeVar

from tqdm import tqdm

from binpick.params import OrchestrationParams

log = logging.getLogger("binpick.fanout")

Job = TypeVar("Job")
Result = TypeVar("Result")

_SHARED: dict[str, Any] = {}


def _init_worker(shared: Any) -> None:
    from binpick.lifetime import die_with_parent

    die_with_parent()  # a killed stage takes its pool workers with it
    _SHARED["value"] = shared


def _call(fn: Callable[[Any, Any], Any], job: Any) -> Any:
    return fn(_SHARED["value"], job)


def worker_count(orchestration: OrchestrationParams) -> int:
    return orchestration.workers or os.cpu_count() or 1


def fan_out(
    fn: Callable[[Any, Job], Result],
    shared: Any,
    jobs: Sequence[Job],
    orchestration: OrchestrationParams,
    desc: str,
    progress: bool = True,
    max_workers: int | None = None,
) -> list[Result]:
    """`[fn(shared, job) for job in jobs]`, spread as `orchestration` says; results in job order.

    max_workers caps the local process pool (e.g. 1 for work that is already multi-threaded);
    a Dask cluster is used as it is.
    """
    if orchestration.task_runner == "dask":
        return _dask(fn, shared, jobs, orchestration, desc, progress)
    workers = min(worker_count(orchestration), max_workers or len(jobs) or 1, len(jobs) or 1)
    results: list[Any] = [None] * len(jobs)
    with tqdm(total=len(jobs), desc=desc, unit="job", disable=not progress) as bar:
        if workers == 1:
            for i, job in enumerate(jobs):
                results[i] = fn(shared, job)
                bar.update()
            return results
        # spawn, not fork: Open3D's and torch's thread pools do not survive a fork.
        with ProcessPoolExecutor(
            workers, mp_context=get_context("spawn"), initializer=_init_worker, initargs=(shared,)
        ) as pool:
            futures = {pool.submit(_call, fn, job): i for i, job in enumerate(jobs)}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    return results


def _dask(
    fn: Callable[[Any, Job], Result],
    shared: Any,
    jobs: Sequence[Job],
    orchestration: OrchestrationParams,
    desc: str,
    progress: bool,
) -> list[Result]:
    """The jobs on a Dask cluster: the one at `dask_address`, else a local cluster of `workers`
    single-threaded processes. Dask's own client, not a Prefect flow: a DVC stage that a Prefect
    flow started must not start flows of its own."""
    from distributed import Client, LocalCluster
    from distributed import as_completed as dask_as_completed

    cluster = None
    if orchestration.dask_address:
        client = Client(orchestration.dask_address)
        where = orchestration.dask_address
    else:
        n = worker_count(orchestration)
        cluster = LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.WARNING
        )
        client = Client(cluster)
        where = f"a local Dask cluster of {n} workers"
    log.info("%s: %d jobs on %s", desc, len(jobs), where)
    try:
        shared_future = client.scatter(shared, broadcast=True)  # sent to each worker once
        futures = [client.submit(fn, shared_future, job, pure=False) for job in jobs]
        index = {f.key: i for i, f in enumerate(futures)}
        results: list[Any] = [None] * len(futures)
        with tqdm(total=len(futures), desc=desc, unit="job", disable=not progress) as bar:
            for future in dask_as_completed(futures):
                results[index[future.key]] = future.result()
                bar.update()
        return results
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
