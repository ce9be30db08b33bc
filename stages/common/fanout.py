"""Fan-out of independent jobs (one scene each) over a local process pool or, through a Prefect
DaskTaskRunner, over a Dask cluster.

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
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker, initargs=(shared,)) as pool:
            futures = {pool.submit(_call, fn, job): i for i, job in enumerate(jobs)}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                bar.update()
    return results


def _dask(fn: Callable[[Any, Job], Result], shared: Any, jobs: Sequence[Job], orchestration: OrchestrationParams, desc: str, progress: bool) -> list[Result]:
    """The jobs as Prefect tasks of one flow whose task runner is a DaskTaskRunner: on the cluster
    at `dask_address`, else on a local cluster of `workers` single-threaded processes."""
    from prefect import flow, task, unmapped
    from prefect.cache_policies import NO_CACHE
    from prefect.futures import as_completed as prefect_as_completed
    from prefect_dask import DaskTaskRunner

    if orchestration.dask_address:
        runner = DaskTaskRunner(address=orchestration.dask_address)
        where = orchestration.dask_address
    else:
        n = worker_count(orchestration)
        runner = DaskTaskRunner(cluster_kwargs={"n_workers": n, "threads_per_worker": 1, "processes": True, "dashboard_address": None, "silence_logs": logging.WARNING})
        where = f"a local Dask cluster of {n} workers"
    log.info("%s: %d jobs on %s", desc, len(jobs), where)
    # No caching: the inputs (meshes, scenes) are large and every job is cheap to hash wrongly.
    job_task = task(fn, name=desc, cache_policy=NO_CACHE, persist_result=False)

    @flow(name=f"fan-out {desc}", task_runner=runner, persist_result=False)
    def fan_out_flow() -> list[Result]:
        futures = job_task.map(unmapped(shared), list(jobs))
        index = {f.task_run_id: i for i, f in enumerate(futures)}
        results: list[Any] = [None] * len(futures)
        with tqdm(total=len(futures), desc=desc, unit="job", disable=not progress) as bar:
            for future in prefect_as_completed(futures):
                results[index[future.task_run_id]] = future.result()
                bar.update()
        return results

    return fan_out_flow()
