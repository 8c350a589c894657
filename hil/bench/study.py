"""``hil bench study``: how fast ``hil study`` runs samples, and what Dask costs per task.

The study: the Arrow 500 X position step of seed 000 (0.5 mm from 250 mm), ``--seconds``
of simulated time (default 1 s) per sample, the table mass drawn within +-10 %
(Monte Carlo), ``--samples`` samples, one sample per task (so every task pays the whole
per-task cost).  In one call:

* **bare**: the same experiment on the first samples' machines, called directly in this
  process (:meth:`~hil.study.experiments.Experiment.run`, no Dask, no store): the median
  seconds per sample, measured before the first round and after every round of the
  1-worker pipeline (the cluster idle meanwhile); and the same inside the worker
  process, outside any task (on its event loop) and as a task; and the Arrow 500 X
  plant's kernel alone over the same PWM periods, called from compiled code;
* **1 worker** and **2 workers**: ``--rounds`` runs each of the whole pipeline (``hil
  study``'s own dispatch: a LocalCluster of that many single-threaded worker processes,
  tasks, the Parquet store), wall time from the first task sent to the last result
  stored: samples per second; each worker's kernels loaded before the clock starts, as
  ``hil study`` does.  The round of median wall time gives the figures; every round is
  in the JSON.
* after each round: **the study's own task size** (the same samples in the tasks ``hil
  study`` would make of them on that cluster: :func:`hil.study.run.task_size` with the
  bare simulation's time), the overhead per sample that a study pays and its scaling; and
  after each 1-worker round **Dask's floor**:
  as many tasks that only sleep as long as the bare simulation: what their wall time
  exceeds the sleep by is Dask's own per-task latency,
  and the CPU the worker's event loop spends per task is Dask's own work, which needs the
  GIL, so a task that holds it (a sample does) waits for all of it.

Rounds, because the machines are shared: one run's wall time moves by several per cent
with the other load, as much as the overhead measured.  Each round is compared with the
bare simulation measured just before and just after it.

Figures: ``bare_s_per_sample`` (goal: <= 30 ms per simulated second) and
``bare_over_plant``, the bare simulation over the plant's kernel alone (goal <= 1.5: the
NC, the drive and the recording cost at most half the plant);
``scaling_ratio_study_task_size`` = rate(2) / (2 rate(1)) with the tasks ``hil study``
makes on each cluster (goal >= 0.9: what a study gains from a second worker), and
``scaling_ratio`` the same with one sample per task (each task's whole cost paid per
sample); ``overhead_pct`` = the median over the rounds of (wall(1) /
samples - bare) / bare, the per-task overhead against a bare simulation of the same
length with one sample per task; ``task_vs_bare_pct`` and ``task_vs_bare_cpu_pct``: the
bare simulation run as a task against here, its wall time (goal <= 5 %) and its
thread's CPU time (the simulation itself slower, or only waiting for a CPU);
``task_vs_worker_bare_pct``: a sample's median time inside a task against the bare
simulation in the same worker process (what the task machinery costs the simulation
itself; the task's time includes building the sample's machine,
``machine_build_s_per_sample``, which the bare time leaves out);
``dispatch_overhead_ms`` = (wall(1) - the samples' own compute time on the worker) /
samples, the same overhead without the simulation's own variation; ``cpu_overhead_pct``:
the CPU time of every process of the 1-worker pipeline (this one with the scheduler, and
the worker) per sample against the bare simulation's, the overhead as it stands when
other work shares the CPUs and the wall-clock figures say little;
``worker_loop_cpu_per_task_s``: the CPU the worker's event-loop thread spends per task
in those rounds; ``dask_floor_pct`` = the floor's loop CPU per task / bare, the share of
the overhead that no code of the study can remove on this machine with one sample per
task; ``overhead_pct_study_task_size``: the overhead per sample with ``hil study``'s
task size (goal <= 5 %).  The load average before and after is reported.
"""

import argparse
import json
import sys


def text(r: dict) -> str:
    """The report in lines."""
    one, two = r["one_worker"], r["two_workers"]
    goals = r["goals"]
    load = (" ".join(f"{x:.2f}" for x in r["load_average_before"]) + ", after "
            + " ".join(f"{x:.2f}" for x in r["load_average_after"]))
    return "\n".join([
        (f"hil bench study: {r['samples']} samples of a {r['simulated_s']:g} s Arrow 500 X "
         f"position step, one per task, {r['cpus']} CPUs"),
        (f"  bare simulation           {r['bare_s_per_sample'] * 1e3:8.1f} ms per sample (goal "
         f"<= {goals['bare_ms_per_s_max'] * r['simulated_s']:g} ms)"),
        (f"  plant kernel alone        {r['plant_kernel_s_per_sample'] * 1e3:8.1f} ms over the "
         f"same PWM periods: bare / plant {r['bare_over_plant']:.2f} (goal <= "
         f"{goals['bare_over_plant_max']:g})"),
        (f"  1 worker                  {one['samples_per_s']:8.2f} samples/s "
         f"({one['wall_s']:.1f} s)"),
        (f"  2 workers                 {two['samples_per_s']:8.2f} samples/s "
         f"({two['wall_s']:.1f} s, {two['distinct_workers']} workers used)"),
        (f"  scaling 1 -> 2 workers    {r['scaling_ratio_study_task_size']:8.2f} x linear in "
         f"hil study's task size ({r['study_task_size']} and "
         f"{r['study_task_size_two_workers']} samples per task; goal >= "
         f"{goals['scaling_ratio_min']:g}); {r['scaling_ratio']:.2f} with one sample per "
         "task"),
        (f"  per-task overhead         {r['overhead_per_task_s'] * 1e3:8.1f} ms = "
         f"{r['overhead_pct']:.1f} % of the bare simulation (rounds "
         + ", ".join(f"{x:.1f}" for x in r["overhead_pct_per_round"]) + " %)"),
        (f"  of it, Dask's own         {r['dask_floor_loop_cpu_per_task_s'] * 1e3:8.1f} ms CPU "
         f"of the worker's event loop per task = {r['dask_floor_pct']:.1f} % (tasks that only "
         f"sleep: {r['dask_floor_wall_per_task_s'] * 1e3:.1f} ms wall beyond the sleep)"),
        (f"  worker's event loop       {r['worker_loop_cpu_per_task_s'] * 1e3:8.1f} ms CPU per "
         "task with the simulation in it"),
        (f"  {str(r['study_task_size']) + ' samples per task':26s}"
         f"{r['overhead_pct_study_task_size']:+8.1f} % per sample (hil study's task size; goal "
         f"<= {goals['overhead_pct_max']:g} %)"),
        (f"  bare in a task / here     {r['task_vs_bare_pct']:+8.1f} % wall, "
         f"{r['task_vs_bare_cpu_pct']:+.1f} % CPU of its thread (goal <= "
         f"{goals['task_vs_bare_pct_max']:g} %; in a task "
         f"{r['bare_in_task_s_per_sample'] * 1e3:.1f} ms, CPU "
         f"{r['bare_in_task_cpu_s_per_sample'] * 1e3:.1f} ms)"),
        (f"  in a task / bare, worker  {r['task_vs_worker_bare_pct']:+8.1f} % (bare in the "
         f"worker {r['bare_in_worker_s_per_sample'] * 1e3:.1f} ms; building a sample's "
         f"machine {r['machine_build_s_per_sample'] * 1e3:.2f} ms)"),
        (f"  dispatch overhead         {r['dispatch_overhead_ms']:8.1f} ms per task (wall - "
         "worker compute)"),
        (f"  CPU per sample            {r['one_worker']['cpu_s'] / r['samples'] * 1e3:8.1f} ms "
         f"in every process of the pipeline, bare {r['bare_cpu_s_per_sample'] * 1e3:.1f} ms: "
         f"{r['cpu_overhead_pct']:+.1f} %"),
        f"  load average              before {load}"])


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil bench study``."""
    # fewer samples and the pipeline's fixed cost per run (about 40 ms on a 2-vCPU VM: the
    # first task's dispatch, the last one's result and store write) is several per cent of
    # the samples' own time
    p.add_argument("--samples", type=int, default=96, help="samples per run (default "
                   "%(default)s)")
    p.add_argument("--seconds", type=float, default=1.0,
                   help="simulated time per sample, s (default %(default)s)")
    p.add_argument("--rounds", type=int, default=3,
                   help="runs of the pipeline per cluster size (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil bench study``: print the report; 0 (the goals are reported, not enforced:
    the figures depend on the machine's other load), 2 on bad input."""
    if args.samples < 2 or not args.seconds > 0.0 or args.rounds < 1:
        print("hil bench study: --samples must be >= 2, --seconds > 0 and --rounds >= 1",
              file=sys.stderr)
        return 2
    from hil.study.benchmark import run

    report = run(args.samples, args.seconds, args.rounds,
                 note=lambda message: print(message, file=sys.stderr, flush=True))
    print(json.dumps(report, indent=1) if args.json else text(report))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python3 -m hil.bench.study ...``: the same as ``hil bench study ...``."""
    parser = argparse.ArgumentParser(prog="hil bench study", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
