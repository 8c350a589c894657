"""Running a study's samples on Dask: the embedded LocalCluster, or an existing cluster.

By default the study starts a :class:`distributed.LocalCluster` on this machine: one
worker process per core (``--workers``), one thread each (the simulation holds the GIL),
scheduler and dashboard on 127.0.0.1, the workers' profiler off, their event loop
uvloop's.  With ``--scheduler tcp://HOST:8786`` it connects to a cluster started
elsewhere (``dask scheduler``, ``dask worker``) and runs unchanged: the machine files and
part programs travel as text (:mod:`hil.study.machine`), so the workers need the same
feeddrive-hil installed, not the study's files.  The dashboard link is printed.

Samples go out as tasks of many samples each, the design's values computed here
(:mod:`hil.study.sampling`); each finished task is written to the Parquet store at once
(:mod:`hil.study.store`), so the results grow while the study runs and survive a kill.
The samples per task are ``--task-size``, or chosen (:func:`dispatch_sized`): the first
sample runs as a task of its own, and its time sizes the others' tasks so that Dask's
cost per task (:data:`TASK_COST_S`) stays within 5 % of their samples' time, at about four
tasks per worker where the samples are many, at most 32 samples.
"""

import importlib.util
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import dask
import numpy as np
import pyarrow as pa
from distributed import Client, Future, LocalCluster, as_completed

from hil.study.evaluate import Job, KernelWarmup, evaluate_chunk
from hil.study.sampling import design, to_values
from hil.study.spec import Study
from hil.study.store import ResultStore

MAX_TASK_SIZE = 32
TASKS_PER_WORKER = 4
#: Dask's cost of one task, s: submitted, run, its table sent back and stored (``hil bench
#: study``'s per-task overhead on a 2-vCPU VM, 8-10 ms)
TASK_COST_S = 0.01
#: the share of its samples' time a task's cost may take
TASK_COST_SHARE = 0.05
#: seconds to wait for a remote cluster's first worker
WORKER_WAIT_S = 60.0
DASHBOARD = "127.0.0.1:8787"
#: the Dask settings of the LocalCluster a study starts (see dask_client)
QUIET_WORKERS = {"distributed.worker.profile.enabled": False,
                 "distributed.admin.tick.interval": "1s",
                 "distributed.admin.system-monitor.interval": "5s",
                 "distributed.worker.memory.monitor-interval": "5s",
                 "distributed.admin.event-loop": "uvloop"}


@dataclass(frozen=True)
class Design:
    """The study's samples: ids (n,) and parameter values (n, P), tuned columns first."""
    ids: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class Batch:
    """What one dispatch did: samples run, failed, wall time (s), and the finished tasks'
    tables (in the order they finished)."""
    done: int
    failed: int
    wall_s: float
    tables: tuple[pa.Table, ...]


def study_design(study: Study) -> Design:
    """The tolerance or sensitivity design of ``study`` (every sample, done or not)."""
    s = study.study
    kind = "saltelli" if s.method == "sensitivity" and s.design == "sobol" else s.design
    u = design(kind, tuple(r.name for r in study.varied), s.samples, s.seed, s.morris_levels)
    return Design(np.arange(u.shape[0]), to_values(u, study.distributions))


def job_of(study: Study, store: ResultStore) -> Job:
    """The task payload of ``study``."""
    return Job(study.machine, study.experiments, study.parameters, study.outputs, store.schema)


@contextmanager
def dask_client(scheduler: str | None, workers: int,
                note: Callable[[str], None]) -> Iterator[Client]:
    """A client of ``scheduler`` (tcp://HOST:PORT), or of a LocalCluster of ``workers``
    single-threaded worker processes; the dashboard link goes to ``note``."""
    cluster = None
    if scheduler:
        client = Client(scheduler, timeout="30s")
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    else:
        # every callback of a worker's event loop takes the GIL from the simulation in the
        # task thread: its statistical profiler (every 10 ms) is off, and the event-loop
        # lag check (20 ms) and the system and memory monitors (0.5 s, 0.1 s) are slowed,
        # on the cluster the study starts itself; uvloop's loop does its socket work in C
        # and takes the GIL less often (hil bench study shows the loop's CPU per task)
        with dask.config.set(QUIET_WORKERS):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=DASHBOARD)
        client = Client(cluster)
    try:
        link = client.dashboard_link
        if importlib.util.find_spec("bokeh") is None:
            link += ("  (its graphs need bokeh, of the 'study' extra: pip install "
                     "'feeddrive-hil[study]'; "
                     f"{link.replace('/status', '/info/main/workers.html')} works without)")
        note(f"dask: {client.scheduler.address}, "
             f"{len(client.scheduler_info()['workers'])} workers, dashboard {link}")
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def warm_workers(client: Client, study: Study) -> float:
    """Register :class:`~hil.study.evaluate.KernelWarmup` (every worker, those joining
    later too); the seconds it took on the present ones."""
    t0 = time.perf_counter()
    client.register_plugin(KernelWarmup(study.machine))
    return time.perf_counter() - t0


def task_size(client: Client, pending: int, requested: int, sample_s: float = 0.0) -> int:
    """Samples per task: ``requested``, or about TASKS_PER_WORKER tasks per worker, and
    with samples of ``sample_s`` (s; 0: not known) enough of them that a task's cost
    (:data:`TASK_COST_S`) is at most :data:`TASK_COST_SHARE` of their time; no fewer
    tasks than workers, no more than MAX_TASK_SIZE samples each."""
    if requested > 0:
        return requested
    workers = max(1, len(client.scheduler_info()["workers"]))
    size = math.ceil(pending / (TASKS_PER_WORKER * workers))
    if sample_s > 0.0:
        size = max(size, math.ceil(TASK_COST_S / (TASK_COST_SHARE * sample_s)))
    return max(1, min(MAX_TASK_SIZE, math.ceil(pending / workers), size))


def send_job(client: Client, job: Job) -> Future:
    """``job`` on every worker once, for all the tasks that follow; under a key of its
    own (a payload sent earlier with the same content and released since must not take
    this one with it)."""
    return client.scatter(job, broadcast=True, hash=False)


def dispatch(client: Client, payload: Future, design_: Design, store: ResultStore, size: int,
             progress: Callable[[int, int], None]) -> Batch:
    """Run the samples of ``design_`` in tasks of ``size`` with the job ``payload``
    (:func:`send_job`); every finished task is written to ``store`` at once;
    ``progress(done, failed)`` after each."""
    t0 = time.perf_counter()
    futures = [client.submit(evaluate_chunk, payload, design_.ids[k:k + size],
                             design_.values[k:k + size], pure=False)
               for k in range(0, len(design_.ids), size)]
    done = failed = 0
    tables = []
    for future in as_completed(futures):
        table = future.result()
        future.release()
        store.write(table)
        tables.append(table)
        done += table.num_rows
        failed += sum(s != "ok" for s in table["status"].to_pylist())
        progress(done, failed)
    return Batch(done, failed, time.perf_counter() - t0, tuple(tables))


def dispatch_sized(client: Client, payload: Future, design_: Design, store: ResultStore,
                   requested: int, progress: Callable[[int, int], None]) -> tuple[Batch, int]:
    """:func:`dispatch` with ``requested`` samples per task, or (``requested`` 0) the
    first sample alone and the others in tasks :func:`task_size` sizes by its compute
    time; the batch of both and the size of the others' tasks."""
    if requested > 0 or design_.ids.size < 2:
        size = task_size(client, design_.ids.size, requested)
        return dispatch(client, payload, design_, store, size, progress), size
    first = dispatch(client, payload, Design(design_.ids[:1], design_.values[:1]), store, 1,
                     progress)
    size = task_size(client, design_.ids.size - 1, 0,
                     float(first.tables[0]["compute_s"][0].as_py()))
    rest = dispatch(client, payload, Design(design_.ids[1:], design_.values[1:]), store, size,
                    lambda done, failed: progress(first.done + done, first.failed + failed))
    return Batch(first.done + rest.done, first.failed + rest.failed,
                 first.wall_s + rest.wall_s, first.tables + rest.tables), size


def pending_of(full: Design, store: ResultStore) -> Design:
    """The samples of ``full`` not yet in ``store``."""
    done = store.done_ids()
    keep = np.array([i not in done for i in full.ids], dtype=bool)
    return Design(full.ids[keep], full.values[keep])
