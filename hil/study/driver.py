"""Running a checked study and reporting on it: what ``hil study`` does once its options
are read (:mod:`hil.study.command`, which imports this module only then, so that the
``hil`` command line starts without Dask, Optuna and SALib)."""

import argparse
import json
import time
from pathlib import Path

from hil.study import summary
from hil.study.progress import Progress
from hil.study.run import (
    dask_client,
    dispatch_sized,
    job_of,
    pending_of,
    send_job,
    study_design,
    warm_workers,
)
from hil.study.spec import Study
from hil.study.store import ResultStore
from hil.study.tuning import run_tuning, tuning_from_store


def _samples(client, study: Study, store: ResultStore, requested: int, progress) -> dict:
    """Run the tolerance or sensitivity design's missing samples."""
    full = study_design(study)
    pending = pending_of(full, store)
    progress.note(f"{full.ids.size} samples: {full.ids.size - pending.ids.size} already in "
                  f"{store.dir}, {pending.ids.size} to run")
    if not pending.ids.size:
        return {"ran": 0}
    progress.start(pending.ids.size, "hil study")
    batch, size = dispatch_sized(client, send_job(client, job_of(study, store)), pending,
                                 store, requested, progress)
    return {"ran": batch.done, "task_size": size, "wall_s": batch.wall_s,
            "samples_per_s": batch.done / batch.wall_s if batch.wall_s > 0 else None}


def run_study(study: Study, out: Path, args: argparse.Namespace, progress: Progress) -> dict:
    """Run (unless ``--report-only``) and report; the summary."""
    store = ResultStore(out, study, args.fresh)
    earlier = out / "summary.json"
    # a report made again keeps what the run that made the results measured
    run: dict = (json.loads(earlier.read_text()).get("run", {})
                 if args.report_only and earlier.exists() else {})
    tuning = None
    if not args.report_only:
        t0 = time.perf_counter()
        with dask_client(args.scheduler, args.workers, progress.note) as client:
            warm = warm_workers(client, study)
            run["workers"] = len(client.scheduler_info()["workers"])
            run["scheduler"] = args.scheduler or "LocalCluster"
            progress.note(f"workers ready ({warm:.1f} s: kernels loaded, machine stepped once)")
            if study.tuning is not None:
                tuning = run_tuning(client, study, store, args.task_size, progress,
                                    progress.note)
            else:
                run.update(_samples(client, study, store, args.task_size, progress))
        run["total_s"] = time.perf_counter() - t0
    if study.tuning is not None and tuning is None:
        tuning = tuning_from_store(study, store)
    return summary.build(out, study, store.read(), tuning, run)
