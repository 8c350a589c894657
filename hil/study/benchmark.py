"""The measurements of ``hil bench study`` (:mod:`hil.bench.study` says what they mean);
imported only when the benchmark runs, so the ``hil`` command line starts without Dask."""

import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from hil.study.keys import overrides_of
from hil.study.progress import Progress
from hil.study.run import (
    dask_client,
    dispatch,
    job_of,
    send_job,
    study_design,
    warm_workers,
)
from hil.study.spec import Study, load_study
from hil.study.store import ResultStore

ARROW = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
BARE_SAMPLES = 5
GOALS = {"scaling_ratio_min": 0.9, "overhead_pct_max": 5.0}

SPEC = """
[study]
name = "hil bench study: Arrow 500 X position step, {seconds:g} s"
machine = "{machine}"
method = "tolerance"
design = "monte_carlo"
seed = 1
samples = {samples}

[experiment]
kind = "step"
at_mm = 250.0
amplitude_mm = 0.5
duration_s = {seconds}
outputs = ["lag_50pct_s", "settling_time_s"]

[vary.table]
mass_kg = {{ tolerance_pct = 10.0 }}
"""


def bench_study(folder: Path, samples: int, seconds: float) -> Study:
    """The benchmark's study file, written into ``folder`` and loaded."""
    path = folder / "bench_study.toml"
    path.write_text(SPEC.format(machine=ARROW.as_posix(), samples=samples, seconds=seconds))
    return load_study(path)


def cpu_seconds() -> float:
    """This process's CPU time (user and system), s."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def bare_seconds(study: Study) -> tuple[float, float]:
    """Median (wall, CPU) seconds of the experiment called directly on the first samples'
    machines."""
    design = study_design(study)
    refs = study.parameters
    exp = study.experiments[0]
    times = []
    for values in design.values[:BARE_SAMPLES + 1]:
        machine = study.machine.build(overrides_of(refs, values))
        t0, c0 = time.perf_counter(), cpu_seconds()
        exp.run(machine, {r.name: v for r, v in zip(refs, values)})
        times.append((time.perf_counter() - t0, cpu_seconds() - c0))
    wall, cpu = np.median(np.array(times[1:]), axis=0)  # the first call loads the kernels
    return float(wall), float(cpu)


def pipeline(study: Study, workers: int, folder: Path, note) -> dict:
    """The whole study on a LocalCluster of ``workers``: wall time, the samples' own time
    on the workers, and the CPU time of every process of the pipeline (this one, with
    the scheduler, and the workers)."""
    store = ResultStore(folder / f"workers_{workers}", study, fresh=True)
    design = study_design(study)
    progress = Progress()
    progress.start(design.ids.size, f"{workers} worker(s)")
    with dask_client(None, workers, note) as client:
        warm_workers(client, study)
        before = cpu_seconds() + sum(client.run(cpu_seconds).values())
        batch = dispatch(client, send_job(client, job_of(study, store)), design, store, 1,
                         progress)
        cpu = cpu_seconds() + sum(client.run(cpu_seconds).values()) - before
    results = store.read()
    compute = float(np.sum(results.table["compute_s"].to_numpy()))
    return {"workers": workers, "samples": batch.done, "failed": batch.failed,
            "wall_s": batch.wall_s, "samples_per_s": batch.done / batch.wall_s,
            "worker_compute_s": compute, "cpu_s": cpu,
            "distinct_workers": len(set(results.table["worker"].to_pylist()))}


def run(samples: int, seconds: float, note=lambda message: None) -> dict:
    """The benchmark (module docstring); the JSON-ready report."""
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="hil-bench-study-") as tmp:
        folder = Path(tmp)
        study = bench_study(folder, samples, seconds)
        before = bare_seconds(study)
        one = pipeline(study, 1, folder, note)
        two = pipeline(study, 2, folder, note)
        after = bare_seconds(study)
    bare, bare_cpu = 0.5 * (before[0] + after[0]), 0.5 * (before[1] + after[1])
    note(f"bare: {bare * 1e3:.1f} ms per {seconds:g} s simulation (before the pipelines "
         f"{before[0] * 1e3:.1f} ms, after {after[0] * 1e3:.1f} ms)")
    per_sample = one["wall_s"] / one["samples"]
    cpu_per_sample = one["cpu_s"] / one["samples"]
    report = {
        "simulated_s": seconds, "samples": samples, "cpus": os.cpu_count(),
        "bare_s_per_sample": bare, "bare_cpu_s_per_sample": bare_cpu,
        "one_worker": one, "two_workers": two,
        "scaling_ratio": two["samples_per_s"] / (2.0 * one["samples_per_s"]),
        "overhead_per_task_s": per_sample - bare,
        "overhead_pct": 100.0 * (per_sample - bare) / bare,
        "cpu_overhead_pct": 100.0 * (cpu_per_sample - bare_cpu) / bare_cpu,
        "dispatch_overhead_ms": 1e3 * (one["wall_s"] - one["worker_compute_s"]) / one["samples"],
        "load_average_before": list(load_before), "load_average_after": list(os.getloadavg()),
        "goals": GOALS}
    report["ok"] = (report["scaling_ratio"] >= GOALS["scaling_ratio_min"]
                    and report["overhead_pct"] <= GOALS["overhead_pct_max"])
    return report
