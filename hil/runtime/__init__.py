"""The real-time HIL runtime: the emulator daemon, the simulated controller as a process,
and the demo that runs both over a transport.

* :mod:`hil.runtime.emulator` — ``hil run``: the plant behind an adapter, one PWM period
  per tick on absolute deadlines, a watchdog, a run folder
  (:mod:`~hil.runtime.run_folder`: ``recording.arrows``, ``events.arrows``,
  ``report.json``);
* :mod:`hil.runtime.watchdog` — the emulator's controller watchdog and its CiA 402 fault;
* :mod:`hil.runtime.recording` — the per-tick rows in a preallocated ring in shared memory
  (:mod:`~hil.runtime.ring`), drained by a writer process
  (:mod:`~hil.runtime.record_writer`, :mod:`~hil.runtime.record_process`) into Arrow IPC
  streams (:mod:`~hil.runtime.stream_file`), read back by :mod:`~hil.runtime.record_reader`
  and exported by :mod:`~hil.runtime.export` (``hil export``: MDF4, CSV);
* :mod:`hil.runtime.soak` — ``hil soak``: memory and lateness over a long run;
* :mod:`hil.runtime.controller_proc` — ``hil controller``: the simulated NC running a part
  program against any adapter, writing ``trace.csv`` and ``summary.json``;
* :mod:`hil.runtime.sync` — how the two loops meet: the controller's alignment to the
  drive's ticks, and which ticks exchanged data as the lock-step simulation does;
* :mod:`hil.runtime.demo` — ``hil demo``: both processes over UDP loopback, compared with
  the lock-step simulation of the same program;
* :mod:`hil.runtime.common` — what the processes share: exit codes, signal handling,
  JSON output, the scheduling request.
"""
