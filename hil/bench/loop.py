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
"""

import sys
from collections.abc import Callable
from pathlib import Path

from hil.rt.cyclictest import CyclictestError, run_cyclictest
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.rt.scheduling import SchedulingRequest, last_cpu, realtime_scheduling

PLANT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
#: kernel calls before the clock starts: compiled code, caches and branch history warm.
PLANT_WARMUP_CALLS = 2000


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
        note: Callable[[str], None] = lambda message: None) -> list[dict]:
    """Benchmark every rate (Hz) for ``seconds`` each; returns the JSON-ready rows.

    Args:
        note: receives a line per finished rate and any reason ``cyclictest_us`` is null.
    """
    if any(not 1 <= r <= 1_000_000 for r in rates):
        raise ValueError(f"rates must be 1..1000000 Hz, got {rates}")
    step = plant_step() if with_plant else _idle_step
    cpu = last_cpu()
    rows = []
    for rate_hz in rates:
        row = {**bench_rate(rate_hz, seconds, step, cpu, note), "with_plant": with_plant}
        rows.append(row)
        ref = row["cyclictest_us"]
        note(f"  {rate_hz:6d} Hz  lateness p99.9 {row['lateness_us']['p999']:8.2f} µs  "
             f"cyclictest p99.9 {'-' if ref is None else format(ref['p999'], '8.2f')} µs  "
             f"overruns {row['overruns']}  CPU {row['cpu_fraction']:.0%}")
    return rows


def main_rows(rates: list[int], seconds: float, with_plant: bool) -> list[dict]:
    """What ``hil bench loop`` prints: :func:`run` with its notes on stderr."""
    return run(rates, seconds, with_plant, note=lambda message: print(message, file=sys.stderr,
                                                                     flush=True))
