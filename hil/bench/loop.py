"""``hil bench loop``: the real-time loop's lateness against cyclictest's, rate by rate.

For each rate a :class:`~hil.rt.loop.RealTimeLoop` runs for ``seconds`` with a trivial
step, or (``with_plant``) one PWM period of the Arrow 500 X axis per tick
(``plant.step(plant.sub_per_pwm)``, compiled and warmed before the clock starts), under
SCHED_FIFO 80 on the last CPU with memory locked, ``/dev/cpu_dma_latency`` at 0, 1 ns
timer slack and the GC frozen, as far as granted.  Right after, in the same call,
``cyclictest`` runs at the same interval, priority and CPU.  The interval is a whole
number of µs (cyclictest's unit): ``period_us`` = round(1e6 / rate_hz) for both.  The
loop's overrun policy is ``"skip"`` because that is what cyclictest does: after a late
wake-up it waits for the next deadline still ahead, so a stall is one late sample, not a
burst of catch-up ticks.

Each row::

    {"rate_hz", "period_us", "with_plant", "ticks", "lateness_us": {"p50", "p99", "p999",
     "max"}, "compute_us": {...}, "overruns", "skipped", "cpu_fraction", "scheduling": {name:
     {"granted", "detail"}}, "cyclictest_us": {"p50", "p99", "p999", "max"} or null}

``cyclictest_us`` is null when cyclictest is not installed (``apt-get install rt-tests``)
or failed; the reason goes to stderr.  The goal: lateness p99.9 at or below
cyclictest's, at no more than half a core (``cpu_fraction`` <= 0.5) at 8 kHz.

With an adapter (``adapter="udp"``, with the plant; issues 12 part 8 and 29) the loop is
``hil run``'s own: the emulator (:class:`~hil.runtime.emulator.Emulator`) on ``config``
(any machine file or manifest; default the Arrow 500 X) at that rate (``None``: its PWM
frequency), its :class:`~hil.runtime.streaming_loop.StreamingLoop` with the steady ticks
in the compiled loop (:mod:`hil.runtime.steady_tick`), the UDP adapter's device end on
127.0.0.1, the recording's rows taken by a thread as the writer process would, its
overrun policy ``hil run``'s (``"count"``), under the same real-time request.  The
controller is ``hil bench tick``'s: a child process (spawned) that enables the drives and
moves them in CSP, one setpoint per period of its own clock.  The row adds ``config``,
``axes``, ``adapter`` (null without one), ``link``: ``{"setpoints", "feedbacks",
"ticks_without_setpoint", "compiled_ticks", "compiled_calls"}`` counted over the run;
``wake_latency_us``, the compiled ticks' wake-up latency (when the sleep before the spin
ended, after its target: what cyclictest measures, and what the spin hides from the
lateness); ``overrun_episodes``, the runs of consecutive overrun ticks after the grace
period, each counted once (one stall is one late cyclictest sample but, under
``"count"``, as many overruns as ticks it held up); and ``cyclictest_beyond``:
``{"slack_us", "samples", "beyond"}``, cyclictest's samples later than the slack a tick
leaves (the period less the tick's p50) in an equally long run at
``cyclictest_interval_us``, the period to the nearest whole µs (cyclictest's unit: 62 µs
for 16 kHz's 62.5).  A stall that cyclictest also sees is the machine's, not the loop's:
issue 29's goal is no more overrun episodes than ``beyond``.
"""

import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from hil.bench import tick as bench_tick
from hil.bench.adapters import server
from hil.progress import COLD_START, COMPILING, Progress
from hil.rt.cyclictest import (
    CyclictestError,
    cyclictest_histogram,
    parse_histogram,
    run_cyclictest,
    samples_beyond,
)
from hil.rt.loop import OverrunPolicy, Percentiles, RealTimeLoop
from hil.rt.scheduling import SchedulingRequest, last_cpu, realtime_scheduling

PLANT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
#: kernel calls before the clock starts: compiled code, caches and branch history warm.
PLANT_WARMUP_CALLS = 2000
#: the adapters the loop can put in the tick
ADAPTERS = ("udp",)


def _idle_step(k: int) -> None:
    """The trivial step: the loop's own cost alone."""


def plant_step(config: Path = PLANT_CONFIG) -> Callable[[int], None]:
    """A step that advances ``config``'s plant (a manifest's first axis) by one PWM
    period, compiled and warmed."""
    from plant import Plant
    from plant.machines import load_machine_set

    with Progress(f"hil bench loop: {COMPILING}", ticking=True):
        plant = Plant(load_machine_set(config).configs[0])
        n_sub = plant.sub_per_pwm
        for _ in range(PLANT_WARMUP_CALLS):
            plant.step(n_sub)

    def step(k: int) -> None:
        plant.step(n_sub)

    return step


def measuring(rate_hz: float, seconds: float) -> Progress:
    """The progress of the measured loop: shown at its start, ended with it, and never
    updated meanwhile (a thread of this process would take the GIL from the loop)."""
    shown = Progress(f"hil bench loop: {rate_hz:g} Hz, the loop measured for {seconds:g} s")
    shown.expect(seconds)
    return shown


def cyclictest_progress(rate_hz: float, interval_us: int, seconds: float) -> Progress:
    """The progress of cyclictest after the loop (a child process: this one only waits)."""
    return Progress(f"hil bench loop: {rate_hz:g} Hz, cyclictest at {interval_us} µs for "
                    f"{seconds:g} s", ticking=True)


def emulator_rate(rate_hz: int | None, seconds: float, config: Path, cpu: int,
                  note: Callable[[str], None]) -> dict:
    """One row with the emulator: ``hil run``'s loop on ``config`` at ``rate_hz`` (None:
    its PWM frequency) behind the UDP adapter's device end, a controller child on the
    other end, under the same real-time request as the plain loop; then cyclictest at the
    same interval (see the module docstring)."""
    from hil.bench.tick import Drain
    from hil.runtime import steady_tick as S
    from hil.runtime.emulator import Emulator, RuntimeConfig, short_gil_switch
    from plant.machines import load_machine_set

    machine = load_machine_set(config)
    rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False, rate_hz=rate_hz,
                       duration_s=seconds)
    with Progress(f"hil bench loop: the emulator loading its compiled kernels and warming "
                  f"up ({COLD_START})", ticking=True):
        emulator = Emulator(rc, machine, log=lambda message: None)
        emulator.open()
    timing = emulator.timing
    period_us = timing.period_ns / 1000
    drain = Drain(emulator.recorder, timing.n_ticks)
    trace = emulator.steady.keep_trace(timing.n_ticks) if emulator.steady is not None \
        else None
    with ExitStack() as stack:
        stack.callback(emulator.endpoint.close)
        with Progress("hil bench loop: the controller process starting", ticking=True):
            stack.enter_context(server(bench_tick.controller, emulator.endpoint.address[1],
                                       len(machine.axes), timing.period_ns))
        drain.start()
        stack.callback(drain.stop)
        with short_gil_switch(), realtime_scheduling(
                SchedulingRequest(cpus=frozenset({cpu}))) as report, \
                measuring(timing.rate_hz, seconds):
            stats = emulator.loop.run()
    ran = drain.compute >= 0
    compute = Percentiles.of_ns_in_us(drain.compute[ran])
    steady = emulator.steady
    # an episode: consecutive ticks that ended after their next deadline (one stall of the
    # machine makes one, however many ticks it holds up under "count")
    late = (drain.lateness + drain.compute > timing.period_ns) & ran
    late[:timing.grace_ticks] = False
    episodes = int(np.count_nonzero(np.diff(late.astype(np.int8), prepend=0) == 1))
    row = {"rate_hz": timing.rate_hz, "period_us": period_us, "config": str(config),
           "axes": len(machine.axes), "ticks": stats.ticks,
           "lateness_us": Percentiles.of_ns_in_us(drain.lateness[ran]).as_dict(),
           "wake_latency_us": None if trace is None else Percentiles.of_ns_in_us(
               trace[trace[:, S.T_WAKE] != 0, S.T_WAKE_LATENCY]).as_dict(),
           "compute_us": compute.as_dict(), "overruns": stats.overruns,
           "overrun_episodes": episodes,
           "skipped": stats.skipped, "cpu_fraction": stats.cpu_fraction,
           "scheduling": report.as_dict(),
           "link": {"setpoints": emulator.setpoints_heard,
                    "feedbacks": emulator.endpoint.stats.sent,
                    "ticks_without_setpoint": stats.ticks - emulator.setpoints_heard,
                    "compiled_ticks": steady.ticks if steady is not None else 0,
                    "compiled_calls": steady.calls if steady is not None else 0}}
    interval_us = round(period_us)  # cyclictest's unit: the nearest whole µs
    if interval_us != period_us:
        note(f"cyclictest takes whole µs: it runs at {interval_us} µs for the period of "
             f"{period_us} µs")
    row["cyclictest_interval_us"] = interval_us
    # a stall cyclictest also sees is the machine's: its wake-ups later than the slack a
    # tick of median compute time leaves would have overrun too
    slack_us = period_us - compute.p50
    try:
        with cyclictest_progress(timing.rate_hz, interval_us, seconds):
            text = cyclictest_histogram(interval_us, seconds, cpu=cpu)
    except CyclictestError as err:
        note(f"cyclictest failed, cyclictest_us is null: {err}")
        text = None
    if text is None:
        note("cyclictest is not installed (apt-get install rt-tests): cyclictest_us is null")
        return {**row, "cyclictest_us": None, "cyclictest_beyond": None}
    beyond, samples = samples_beyond(text, slack_us)
    return {**row, "cyclictest_us": parse_histogram(text).as_dict(),
            "cyclictest_beyond": {"slack_us": slack_us, "samples": samples,
                                  "beyond": beyond}}


def bench_rate(rate_hz: int, seconds: float, step: Callable[[int], None], cpu: int,
               note: Callable[[str], None]) -> dict:
    """One row: the loop at ``rate_hz`` on ``cpu``, then cyclictest at the same interval."""
    period_us = round(1e6 / rate_hz)
    loop = RealTimeLoop(period_us * 1000, step, duration_s=seconds, policy=OverrunPolicy("skip"))
    with realtime_scheduling(SchedulingRequest(cpus=frozenset({cpu}))) as report, \
            measuring(rate_hz, seconds):
        stats = loop.run()
    try:
        with cyclictest_progress(rate_hz, period_us, seconds):
            reference = run_cyclictest(period_us, seconds, cpu=cpu)
        if reference is None:
            note("cyclictest is not installed (apt-get install rt-tests): cyclictest_us is null")
    except CyclictestError as err:
        note(f"cyclictest failed, cyclictest_us is null: {err}")
        reference = None
    return {"rate_hz": rate_hz, "period_us": period_us, "ticks": stats.ticks,
            "lateness_us": stats.lateness_us.as_dict(), "compute_us": stats.compute_us.as_dict(),
            "overruns": stats.overruns, "skipped": stats.skipped,
            "cpu_fraction": stats.cpu_fraction,
            "scheduling": report.as_dict(),
            "cyclictest_us": None if reference is None else reference.as_dict()}


def run(rates: list[int | None], seconds: float, with_plant: bool,
        note: Callable[[str], None] = lambda message: None, adapter: str | None = None,
        config: Path = PLANT_CONFIG) -> list[dict]:
    """Benchmark every rate (Hz) for ``seconds`` each; returns the JSON-ready rows.

    Args:
        rates: with an adapter, None stands for the machine's PWM frequency.
        note: receives a line per finished rate and any reason ``cyclictest_us`` is null.
        adapter: None, or one of :data:`ADAPTERS` (needs ``with_plant``): the emulator
            (``hil run``'s loop) on ``config`` behind that adapter's device end, a
            controller child on the other.
        config: the machine file or manifest of the plant (with an adapter: of the
            emulator).
    """
    if any(r is not None and not 1 <= r <= 1_000_000 for r in rates) or (
            adapter is None and None in rates):
        raise ValueError(f"rates must be 1..1000000 Hz, got {rates}")
    if adapter is not None and not with_plant:
        raise ValueError(f"adapter={adapter!r} needs with_plant: the adapter carries the "
                         f"plant's setpoints and feedback")
    if adapter is not None and adapter not in ADAPTERS:
        raise ValueError(f"adapter must be one of {ADAPTERS}, got {adapter!r}")
    cpu = last_cpu()
    rows = []
    shared = plant_step(config) if with_plant and adapter is None else _idle_step
    for rate_hz in rates:
        if adapter is not None:
            row = {**emulator_rate(rate_hz, seconds, config, cpu, note), "with_plant": True,
                   "adapter": adapter}
        else:
            row = {**bench_rate(rate_hz, seconds, shared, cpu, note),
                   "with_plant": with_plant, "adapter": None, "link": None}
        rows.append(row)
        ref = row["cyclictest_us"]
        note(f"  {row['rate_hz']:8g} Hz  lateness p99.9 {row['lateness_us']['p999']:8.2f} µs  "
             f"cyclictest p99.9 {'-' if ref is None else format(ref['p999'], '8.2f')} "
             f"µs  overruns {row['overruns']}  CPU {row['cpu_fraction']:.0%}")
    return rows


def main_rows(rates: list[int | None], seconds: float, with_plant: bool,
              adapter: str | None = None, config: Path = PLANT_CONFIG) -> list[dict]:
    """What ``hil bench loop`` prints: :func:`run` with its notes on stderr."""
    return run(rates, seconds, with_plant, adapter=adapter, config=config,
               note=lambda message: print(message, file=sys.stderr, flush=True))
