"""What a Dask task does: simulate a chunk of samples and return them as one Arrow table.

A task carries the :class:`Job` (the machine as text, the experiments, the parameter
names; sent to every worker once) and a chunk of sample ids with their parameter values.
Per sample it builds the machine with the sample's keys, runs every experiment and keeps
the outputs; a sample that fails (a machine-file rule refuses the combination, the run
raises) is a row with its reason in ``status`` and NaN outputs, not a failed task.

:class:`KernelWarmup` is registered on every worker, those of a remote cluster that join
later included: it loads the lock-step's compiled kernels (numba's on-disk cache, compiled
on the first use on that machine: the plant's, the drives', the NC's and the compiled
blocks') by running the study's machine (:func:`hil.sim.warm`), so each worker compiles
once, before its first task, not inside one.
"""

import math
import time
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
from distributed import WorkerPlugin, get_worker

from hil.sim import warm
from hil.study.experiments import Experiment
from hil.study.keys import KeyRef, overrides_of
from hil.study.machine import MachineSource


@dataclass(frozen=True)
class Job:
    """Everything a task needs besides its samples.

    Attributes:
        machine: the machine as text (None for analytic experiments).
        experiments: run in order on every sample.
        parameters: the value columns' keys, in order.
        outputs: the output columns in order.
        schema: the result table's columns (:func:`hil.study.store.schema`).
    """
    machine: MachineSource | None
    experiments: tuple[Experiment, ...]
    parameters: tuple[KeyRef, ...]
    outputs: tuple[str, ...]
    schema: pa.Schema


def _worker_name() -> str:
    try:
        return str(get_worker().name)
    except ValueError:  # not inside a Dask worker (a direct call)
        return "local"


def evaluate_sample(job: Job, values: np.ndarray) -> tuple[dict, dict]:
    """(output name -> value, curve column -> values) of one sample; raises what the
    machine-file loader or the run raises."""
    machine = None
    if job.machine is not None:
        machine_refs = tuple(r for r in job.parameters if r.section != "analytic")
        picked = [v for r, v in zip(job.parameters, values) if r.section != "analytic"]
        machine = job.machine.build(overrides_of(machine_refs, picked))
    named = {r.name: float(v) for r, v in zip(job.parameters, values)}
    outputs, curves = {}, {}
    for i, exp in enumerate(job.experiments):
        m = exp.run(machine, named)
        outputs.update(m.values)
        if m.curve is not None:
            curves[f"curve_{i}"] = m.curve
    return outputs, curves


def evaluate_chunk(job: Job, ids: np.ndarray, values: np.ndarray) -> pa.Table:
    """The samples ``ids`` (shape (n,)) with parameter values ``values`` (n, P) as one
    table of ``job.schema``."""
    rows = {name: [] for name in job.schema.names}
    worker = _worker_name()
    curve_names = [n for n in job.schema.names if n.startswith("curve_")]
    for sample_id, row in zip(ids, values):
        started = time.time()
        t0 = time.perf_counter()
        try:
            outputs, curves = evaluate_sample(job, row)
            status = "ok"
        except Exception as exc:  # noqa: BLE001 -- a failed sample is a result, with its reason
            outputs, curves, status = {}, {}, f"{type(exc).__name__}: {exc}"
        rows["sample_id"].append(int(sample_id))
        rows["status"].append(status)
        rows["worker"].append(worker)
        rows["started_utc"].append(int(started * 1e6))
        rows["finished_utc"].append(int(time.time() * 1e6))
        rows["compute_s"].append(time.perf_counter() - t0)
        for ref, v in zip(job.parameters, row):
            rows[ref.name].append(float(v))
        for name in job.outputs:
            rows[name].append(float(outputs.get(name, math.nan)))
        for name in curve_names:
            curve = curves.get(name)
            rows[name].append(None if curve is None else np.asarray(curve, np.float32).tolist())
    return pa.table(rows, schema=job.schema)


class KernelWarmup(WorkerPlugin):
    """Load (or compile, once per machine) the lock-step's kernels on a worker as it
    starts, by running the study's machine (module docstring)."""

    name = "hil-study-kernel-warmup"

    def __init__(self, machine: MachineSource | None):
        self.machine = machine

    def setup(self, worker) -> None:
        if self.machine is None:
            return
        warm(self.machine.build())
