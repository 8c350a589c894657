"""Hard-timed execution on a general-purpose Linux machine.

* :mod:`hil.rt.clock` — waiting on absolute monotonic deadlines (sleep, then spin), and
  a simulated clock for deterministic tests;
* :mod:`hil.rt.scheduling` — SCHED_FIFO, CPU affinity, ``mlockall``, timer slack,
  ``/dev/cpu_dma_latency`` and a frozen GC, each requested, reported and undone; a
  process's helper threads given real-time priority below the loop on its CPU;
* :mod:`hil.rt.loop` — :class:`~hil.rt.loop.RealTimeLoop`: one step per period on
  absolute deadlines, per-tick lateness and compute time in preallocated buffers, an
  overrun policy (the tick discipline, :func:`~hil.rt.loop.run_ticks`, is shared with
  the emulator's :class:`~hil.runtime.streaming_loop.StreamingLoop`);
* :mod:`hil.rt.cyclictest` — the reference: Debian rt-tests' ``cyclictest`` at the same
  interval, its histogram reduced to the same percentiles.
"""
