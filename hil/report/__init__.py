"""Latency and jitter reports of emulator runs (``hil report RUN [--controller DIR]``).

* :mod:`hil.report.latency` — :class:`~hil.report.latency.RunData` and
  :func:`~hil.report.latency.load_run` (the run folder's files and keys, the round trips
  paired with the controller's ``controller.npz``), the report
  (:func:`~hil.report.latency.build_report`, :func:`~hil.report.latency.write_report`);
* :mod:`hil.report.baseline` — the cyclictest baseline at the run's period, histogram kept;
* :mod:`hil.report.render` — the Markdown page and the lateness histogram;
* :mod:`hil.report.host` — the host fingerprint: kernel, PREEMPT_RT, CPU, governors,
  virtualisation, Python and numba.
"""
