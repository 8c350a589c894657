"""Studies over many simulated machines: tolerance, sensitivity and tuning, on Dask.

``hil study SPEC.toml`` (:mod:`hil.study.command`, :mod:`hil.study.driver`) reads a study
file (:mod:`hil.study.spec`: the machine, the experiment, the keys that vary and how),
draws the samples (:mod:`hil.study.sampling`), runs them as Dask tasks on a LocalCluster or
an existing cluster (:mod:`hil.study.run`, :mod:`hil.study.evaluate`), streams the results
to a Parquet dataset (:mod:`hil.study.store`), and reports percentiles, Sobol or Morris
indices (:mod:`hil.study.sensitivity`) or the best tuning (:mod:`hil.study.tuning`) with
figures (:mod:`hil.study.report`, :mod:`hil.study.summary`).  ``hil bench study``
(:mod:`hil.bench.study`, :mod:`hil.study.benchmark`) measures the pipeline itself.
"""
