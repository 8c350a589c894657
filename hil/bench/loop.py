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

With an adapter (``adapter="udp"``, with the plant; issue 12 part 8) the tick is the
emulator's real one, :meth:`hil.runtime.emulator.Emulator.step` on the Arrow 500 X at
that rate: the UDP adapter's device end on 127.0.0.1, the watchdog, the drive (its
compiled cycle, and the tick compiled from the datagram to the answer where it applies,
:mod:`hil.runtime.steady_tick`), the feedback, the row written into the recording's ring
(drained between ticks, as the recording's writer would).  The controller is
``hil bench tick``'s: a child process (spawned) that enables the drive and moves it in
CSP, one setpoint per period of its own clock.  The row adds ``adapter`` (null without
one) and ``link``: ``{"setpoints", "feedbacks", "ticks_without_setpoint",
"compiled_ticks"}`` counted over the run.
"""

import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from hil.bench import tick as bench_tick
from hil.bench.adapters import server
from hil.rt.cyclictest import CyclictestError, run_cyclictest
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.rt.scheduling import SchedulingRequest, last_cpu, realtime_scheduling

PLANT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
#: kernel calls before the clock starts: compiled code, caches and branch history warm.
PLANT_WARMUP_CALLS = 2000
#: the adapters the loop can put in the tick
ADAPTERS = ("udp",)


def _idle_step(k: int) -> None:
    """The trivial step: the loop's own cost alone."""


def plant_step(config: Path = PLANT_CONFIG) -> Callable[[int], None]:
    """A step that advances ``config``'s plant by one PWM period, compiled and warmed."""
    from plant import Plant

    plant = Plant.from_file(config)
    n_sub = plant.sub_per_pwm
    for _ in range(PLANT_WARMUP_CALLS):
        plant.step(n_sub)

    def step(k: int) -> None:
        plant.step(n_sub)

    return step


class EmulatorTick:
    """The emulator's real tick at ``rate_hz`` behind a UDP device end (see the module
    docstring); call it with the tick's index.

    Args:
        rate_hz: the loop's rate (the drive cycles per tick follow from the PWM's).
        config: the machine file.
    """

    def __init__(self, rate_hz: int, config: Path = PLANT_CONFIG):
        from hil.runtime.emulator import Emulator, RuntimeConfig
        from plant.machines import load_machine_set

        rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False, rate_hz=rate_hz)
        self.emulator = Emulator(rc, load_machine_set(config), log=lambda message: None)
        self.emulator.open()
        self.recorder = self.emulator.recorder
        self.period_ns = self.emulator.timing.period_ns
        self._counted = (0, 0, 0, 0)
        self.ticks = 0

    @property
    def port(self) -> int:
        return self.emulator.endpoint.address[1]

    def __call__(self, k: int) -> None:
        self.emulator.step(k)
        self.recorder.end_tick(k, 0, 0)
        self.recorder.release(self.recorder.committed)  # the writer's part
        self.ticks += 1

    def link(self) -> dict:
        """The counts since the last call: setpoints heard, feedbacks sent, ticks that
        heard none, ticks the compiled tick ran (silent ones included)."""
        em = self.emulator
        now = (em.setpoints_heard, em.endpoint.stats.sent, self.ticks,
               em.steady.ticks if em.steady is not None else 0)
        heard, sent, ticks, compiled = (a - b for a, b in zip(now, self._counted))
        self._counted = now
        return {"setpoints": heard, "feedbacks": sent, "ticks_without_setpoint": ticks - heard,
                "compiled_ticks": compiled}

    def close(self) -> None:
        self.emulator.endpoint.close()


def adapter_step(stack: ExitStack, adapter: str, rate_hz: int,
                 config: Path = PLANT_CONFIG) -> EmulatorTick:
    """The emulator behind ``adapter``'s device end with its controller child running,
    both closed by ``stack``; the emulator warm (compiled code loaded) before it is
    returned, and the link counts zeroed."""
    if adapter not in ADAPTERS:
        raise ValueError(f"adapter must be one of {ADAPTERS}, got {adapter!r}")
    step = EmulatorTick(rate_hz, config)
    stack.callback(step.close)
    stack.enter_context(server(bench_tick.controller, step.port, 1, step.period_ns))
    step.link()
    return step


def bench_rate(rate_hz: int, seconds: float, step: Callable[[int], None], cpu: int,
               note: Callable[[str], None]) -> dict:
    """One row: the loop at ``rate_hz`` on ``cpu``, then cyclictest at the same interval."""
    period_us = round(1e6 / rate_hz)
    loop = RealTimeLoop(period_us * 1000, step, duration_s=seconds, policy=OverrunPolicy("skip"))
    with realtime_scheduling(SchedulingRequest(cpus=frozenset({cpu}))) as report:
        stats = loop.run()
    try:
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


def run(rates: list[int], seconds: float, with_plant: bool,
        note: Callable[[str], None] = lambda message: None, adapter: str | None = None
        ) -> list[dict]:
    """Benchmark every rate (Hz) for ``seconds`` each; returns the JSON-ready rows.

    Args:
        note: receives a line per finished rate and any reason ``cyclictest_us`` is null.
        adapter: None, or one of :data:`ADAPTERS` (needs ``with_plant``): the tick is the
            emulator's behind that adapter's device end, a controller child on the other.
    """
    if any(not 1 <= r <= 1_000_000 for r in rates):
        raise ValueError(f"rates must be 1..1000000 Hz, got {rates}")
    if adapter is not None and not with_plant:
        raise ValueError(f"adapter={adapter!r} needs with_plant: the adapter carries the "
                         f"plant's setpoints and feedback")
    cpu = last_cpu()
    rows = []
    shared = plant_step() if with_plant and adapter is None else _idle_step
    for rate_hz in rates:
        with ExitStack() as stack:  # the emulator runs at the row's rate
            linked = adapter_step(stack, adapter, rate_hz) if adapter is not None else None
            row = {**bench_rate(rate_hz, seconds, linked or shared, cpu, note),
                   "with_plant": with_plant, "adapter": adapter,
                   "link": None if linked is None else linked.link()}
            rows.append(row)
        ref = row["cyclictest_us"]
        note(f"  {rate_hz:6d} Hz  lateness p99.9 {row['lateness_us']['p999']:8.2f} µs  "
             f"cyclictest p99.9 {'-' if ref is None else format(ref['p999'], '8.2f')} "
             f"µs  overruns {row['overruns']}  CPU {row['cpu_fraction']:.0%}")
    return rows


def main_rows(rates: list[int], seconds: float, with_plant: bool,
              adapter: str | None = None) -> list[dict]:
    """What ``hil bench loop`` prints: :func:`run` with its notes on stderr."""
    return run(rates, seconds, with_plant, adapter=adapter,
               note=lambda message: print(message, file=sys.stderr, flush=True))
