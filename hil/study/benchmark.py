"""The measurements of ``hil bench study`` (:mod:`hil.bench.study` says what they mean);
imported only when the benchmark runs, so the ``hil`` command line starts without Dask."""

import math
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from distributed import as_completed

from hil.bench.plant import kernel_calls
from hil.study.keys import overrides_of
from hil.study.progress import Progress
from hil.study.run import (
    dask_client,
    dispatch,
    job_of,
    send_job,
    study_design,
    task_size,
    warm_workers,
)
from hil.study.spec import Study, load_study
from hil.study.store import ResultStore
from plant import Plant
from plant import layout as L
from plant.config import load_machine

ARROW = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
BARE_SAMPLES = 5
GOALS = {"scaling_ratio_min": 0.9, "overhead_pct_max": 5.0, "bare_ms_per_s_max": 30.0,
         "bare_over_plant_max": 1.5, "task_vs_bare_pct_max": 5.0}

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


def bare_seconds(study: Study) -> tuple[float, float, float]:
    """Median (wall, CPU) seconds of the experiment called directly on the first samples'
    machines (CPU: this thread's, the simulation's own), and the median wall seconds of
    building a sample's machine (which a task does and the bare time leaves out)."""
    design = study_design(study)
    refs = study.parameters
    exp = study.experiments[0]
    times = []
    for values in design.values[:BARE_SAMPLES + 1]:
        t_build = time.perf_counter()
        machine = study.machine.build(overrides_of(refs, values))
        t0, c0 = time.perf_counter(), time.thread_time()
        exp.run(machine, {r.name: v for r, v in zip(refs, values)})
        times.append((time.perf_counter() - t0, time.thread_time() - c0, t0 - t_build))
    # the first call loads the kernels (and parses the machine file)
    wall, cpu, build = np.median(np.array(times[1:]), axis=0)
    return float(wall), float(cpu), float(build)


def plant_seconds(seconds: float) -> float:
    """Median seconds of the Arrow 500 X plant's kernel alone over the PWM periods of
    ``seconds`` of simulated time, called once per period from compiled code (what the
    lock-step's bare simulation steps, without the NC, the drive and the recording)."""
    plant = Plant(load_machine(ARROW), table_pos=0.25)
    plant.inp[L.I_ENABLE] = 1.0
    arrays = (plant.params, plant.state, plant.inp, plant.out, plant.sub_per_pwm)
    periods = math.ceil(seconds / plant.pwm_period)
    kernel_calls(*arrays, 1)
    times = []
    for _ in range(BARE_SAMPLES):
        t0 = time.perf_counter()
        kernel_calls(*arrays, periods)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def loop_cpu_seconds(client) -> float:
    """The CPU time of every worker's event-loop thread so far, s (``client.run`` calls
    its function on that thread)."""
    return sum(client.run(time.thread_time).values())


def pipeline_round(client, study: Study, folder: Path, label: str, size: int = 1) -> dict:
    """One run of the whole study on ``client``'s cluster (``size`` samples per task, a
    fresh store in ``folder``): wall time, the samples' own time on the workers, the CPU
    time of every process of the pipeline (this one, with the scheduler, and the workers)
    and of the workers' event-loop threads."""
    store = ResultStore(folder, study, fresh=True)
    design = study_design(study)
    progress = Progress()
    progress.start(design.ids.size, label)
    before = cpu_seconds() + sum(client.run(cpu_seconds).values())
    loop_before = loop_cpu_seconds(client)
    batch = dispatch(client, send_job(client, job_of(study, store)), design, store, size,
                     progress)
    loop = loop_cpu_seconds(client) - loop_before
    cpu = cpu_seconds() + sum(client.run(cpu_seconds).values()) - before
    results = store.read()
    compute = results.table["compute_s"].to_numpy()
    return {"samples": batch.done, "failed": batch.failed, "task_size": size,
            "tasks": math.ceil(batch.done / size), "wall_s": batch.wall_s,
            "samples_per_s": batch.done / batch.wall_s,
            "worker_compute_s": float(np.sum(compute)),
            "worker_compute_median_s": float(np.median(compute)), "cpu_s": cpu,
            "worker_loop_cpu_s": loop,
            "distinct_workers": len(set(results.table["worker"].to_pylist()))}


def dask_floor_round(client, tasks: int, seconds: float) -> dict:
    """Dask's own cost per task on ``client``'s cluster: ``tasks`` tasks that each sleep
    ``seconds`` (the GIL free, nothing simulated), sent, fetched and released as
    :func:`~hil.study.run.dispatch` does.  Wall time per task beyond the sleep, s, and
    the workers' event-loop CPU per task, s: all of that work needs the GIL, so a task
    that holds it, as a sample does, waits for it (or the loop's work for the task)."""
    loop_before = loop_cpu_seconds(client)
    t0 = time.perf_counter()
    futures = [client.submit(time.sleep, seconds, pure=False) for _ in range(tasks)]
    for future in as_completed(futures):
        future.result()
        future.release()
    wall = time.perf_counter() - t0
    return {"wall_beyond_sleep_s": wall / tasks - seconds,
            "worker_loop_cpu_s": (loop_cpu_seconds(client) - loop_before) / tasks}


def cluster_rounds(study: Study, workers: int, rounds: int, folder: Path, note,
                   sample_s: float, measure_bare: bool) -> dict:
    """``rounds`` runs of the study on one LocalCluster of ``workers``, one sample per
    task, each followed by the same study in the task size ``hil study`` picks for samples
    of ``sample_s`` (s) on this cluster.  With ``measure_bare``, after each: Dask's floor
    (:func:`dask_floor_round`, tasks sleeping ``sample_s``), and the bare simulation in
    this process and in a worker (the cluster idle meanwhile).  The round of median wall
    time is the figure; every round is kept."""
    runs, own_size, floors, bare_here, bare_worker, bare_task = [], [], [], [], [], []
    with dask_client(None, workers, note) as client:
        warm_workers(client, study)
        size = task_size(client, study.study.samples, 0, sample_s)
        for r in range(rounds):
            label = f"{workers} worker(s), round {r + 1}/{rounds}"
            runs.append(pipeline_round(client, study, folder / f"workers_{workers}_{r}",
                                       label))
            own_size.append(pipeline_round(client, study, folder / f"own_size_{workers}_{r}",
                                           f"{label}, {size} samples per task", size))
            if not measure_bare:
                continue
            floors.append(dask_floor_round(client, study.study.samples, sample_s))
            bare_here.append(bare_seconds(study))
            bare_worker.append(next(iter(client.run(bare_seconds, study).values())))
            bare_task.append(client.submit(bare_seconds, study, pure=False).result())
    median = sorted(runs, key=lambda x: x["wall_s"])[len(runs) // 2]
    out = {"workers": workers, **median, "rounds": runs, "study_task_size_rounds": own_size}
    if measure_bare:
        out.update({"dask_floor_rounds": floors,
                    "bare_s_after_rounds": [b[0] for b in bare_here],
                    "bare_cpu_s_after_rounds": [b[1] for b in bare_here],
                    "build_s_after_rounds": [b[2] for b in bare_here],
                    "bare_in_worker_s_after_rounds": [b[0] for b in bare_worker],
                    "bare_in_task_after_rounds": [b[:2] for b in bare_task]})
    return out


def _median_rate(cluster: dict) -> float:
    """Samples per second of the median round in ``hil study``'s task size."""
    return float(np.median([rd["samples_per_s"] for rd in cluster["study_task_size_rounds"]]))


def run(samples: int, seconds: float, rounds: int = 3, note=lambda message: None) -> dict:
    """The benchmark (module docstring); the JSON-ready report."""
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="hil-bench-study-") as tmp:
        folder = Path(tmp)
        study = bench_study(folder, samples, seconds)
        first = bare_seconds(study)
        plant_s = plant_seconds(seconds)
        one = cluster_rounds(study, 1, rounds, folder, note, first[0], measure_bare=True)
        two = cluster_rounds(study, 2, rounds, folder, note, first[0], measure_bare=False)
    bares = [first[0], *one["bare_s_after_rounds"]]
    bare_cpus = [first[1], *one["bare_cpu_s_after_rounds"]]
    # each round against the bare simulation measured just before and just after it
    around = [0.5 * (bares[i] + bares[i + 1]) for i in range(rounds)]
    extra = [rd["wall_s"] / rd["samples"] - b for rd, b in zip(one["rounds"], around)]
    extra_own = [rd["wall_s"] / rd["samples"] - b
                 for rd, b in zip(one["study_task_size_rounds"], around)]
    floor_wall = float(np.median([f["wall_beyond_sleep_s"] for f in one["dask_floor_rounds"]]))
    floor_loop = float(np.median([f["worker_loop_cpu_s"] for f in one["dask_floor_rounds"]]))
    bare, bare_cpu = float(np.median(bares)), float(np.median(bare_cpus))
    in_worker = float(np.median(one["bare_in_worker_s_after_rounds"]))
    in_task, in_task_cpu = np.median(np.array(one["bare_in_task_after_rounds"]), axis=0)
    note(f"bare: {bare * 1e3:.1f} ms per {seconds:g} s simulation here (each: "
         + ", ".join(f"{b * 1e3:.1f}" for b in bares) + f" ms), {in_worker * 1e3:.1f} ms "
         "in a worker outside any task")
    cpu_per_sample = one["cpu_s"] / one["samples"]
    report = {
        "simulated_s": seconds, "samples": samples, "rounds": rounds, "cpus": os.cpu_count(),
        "bare_s_per_sample": bare, "bare_cpu_s_per_sample": bare_cpu,
        "bare_in_worker_s_per_sample": in_worker,
        "plant_kernel_s_per_sample": plant_s, "bare_over_plant": bare / plant_s,
        "bare_in_task_s_per_sample": float(in_task),
        "bare_in_task_cpu_s_per_sample": float(in_task_cpu),
        "task_vs_bare_pct": 100.0 * (in_task - bare) / bare,
        "task_vs_bare_cpu_pct": 100.0 * (in_task_cpu - bare_cpu) / bare_cpu,
        "machine_build_s_per_sample": float(np.median([first[2], *one["build_s_after_rounds"]])),
        "one_worker": one, "two_workers": two,
        "scaling_ratio": two["samples_per_s"] / (2.0 * one["samples_per_s"]),
        "scaling_ratio_study_task_size": _median_rate(two) / (2.0 * _median_rate(one)),
        "study_task_size_two_workers": two["study_task_size_rounds"][0]["task_size"],
        "overhead_pct_per_round": [100.0 * e / b for e, b in zip(extra, around)],
        "overhead_pct": 100.0 * float(np.median([e / b for e, b in zip(extra, around)])),
        "overhead_per_task_s": float(np.median(extra)),
        "worker_loop_cpu_per_task_s": float(np.median(
            [rd["worker_loop_cpu_s"] / rd["tasks"] for rd in one["rounds"]])),
        "dask_floor_wall_per_task_s": floor_wall,
        "dask_floor_loop_cpu_per_task_s": floor_loop,
        "dask_floor_pct": 100.0 * floor_loop / bare,
        "study_task_size": one["study_task_size_rounds"][0]["task_size"],
        "overhead_pct_study_task_size": 100.0 * float(np.median(
            [e / b for e, b in zip(extra_own, around)])),
        "task_vs_worker_bare_pct": 100.0 * (one["worker_compute_median_s"] - in_worker)
        / in_worker,
        "cpu_overhead_pct": 100.0 * (cpu_per_sample - bare_cpu) / bare_cpu,
        "dispatch_overhead_ms": 1e3 * (one["wall_s"] - one["worker_compute_s"]) / one["samples"],
        "load_average_before": list(load_before), "load_average_after": list(os.getloadavg()),
        "goals": GOALS}
    report["ok"] = (report["scaling_ratio_study_task_size"] >= GOALS["scaling_ratio_min"]
                    and report["overhead_pct_study_task_size"] <= GOALS["overhead_pct_max"]
                    and 1e3 * bare / seconds <= GOALS["bare_ms_per_s_max"]
                    and report["bare_over_plant"] <= GOALS["bare_over_plant_max"]
                    and report["task_vs_bare_pct"] <= GOALS["task_vs_bare_pct_max"])
    return report
