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
emulator's real workload: the device end of a UDP link on 127.0.0.1 takes the setpoints
that arrived (none waits: the socket is polled), the plant runs one PWM period on the
latest one's current setpoint, and the feedback (sequence number, encoder and scale
counts, speed, measured current, time) goes back.  The controller is a child process
(spawned) that answers every feedback with the next setpoint, a square wave of
:data:`SQUARE_A` amperes changing sign every :data:`SQUARE_HALF` setpoints, so the axis
moves to and fro.  The row adds ``adapter`` (null without one) and ``link``:
``{"setpoints", "feedbacks", "ticks_without_setpoint"}`` counted over the run, the last
saying how often the controller had not answered in time for the next tick.
"""

import select
import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from hil.bench.adapters import server
from hil.rt.cyclictest import CyclictestError, run_cyclictest
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.rt.scheduling import SchedulingRequest, last_cpu, realtime_scheduling
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.codec import U32
from io_adapters.messages import MODE_CST

PLANT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
#: kernel calls before the clock starts: compiled code, caches and branch history warm.
PLANT_WARMUP_CALLS = 2000
#: the adapters the loop can put in the tick
ADAPTERS = ("udp",)
#: the controller child's current setpoint: +-SQUARE_A A, sign changing every SQUARE_HALF
#: setpoints (50 ms at 8 kHz: the Arrow 500 X moves a few mm to and fro)
SQUARE_A = 1.0
SQUARE_HALF = 400


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


def square_wave_controller(url: str, conn) -> None:
    """The controller child: answers every feedback on ``url`` with the next setpoint
    (current mode, :data:`SQUARE_A` square wave) until ``conn`` says stop."""
    with open_endpoint(url, "controller") as ep:
        sp, fb = Setpoint(controlword=0x000F, mode=MODE_CST), Feedback()
        ep.send_setpoint(sp)
        conn.send(None)
        while conn not in select.select((ep, conn), (), ())[0]:
            while ep.recv_feedback(fb, 0):
                sp.seq = (fb.seq + 1) & U32
                sp.iq_ref_a = SQUARE_A if (sp.seq // SQUARE_HALF) % 2 == 0 else -SQUARE_A
                ep.send_setpoint(sp)


class PlantOverAdapter:
    """The tick with the adapter: poll the setpoints, one PWM period of the plant, send
    the feedback (see the module docstring); counts what went over the link.

    Args:
        endpoint: the device end of the link, open.
        config: the machine file.
    """

    def __init__(self, endpoint, config: Path = PLANT_CONFIG):
        from plant import Plant
        from plant.layout import P_ENC_COUNTS_PER_RAD

        self.endpoint = endpoint
        self.plant = Plant.from_file(config)
        self._counts_per_rad = float(self.plant.params[P_ENC_COUNTS_PER_RAD])
        self.setpoint, self.feedback = Setpoint(), Feedback()
        self.setpoints = self.feedbacks = self.ticks_without_setpoint = 0

    def __call__(self, k: int) -> None:
        ep, sp, fb, plant = self.endpoint, self.setpoint, self.feedback, self.plant
        fresh = 0
        while ep.recv_setpoint(sp, 0):
            fresh += 1
        self.setpoints += fresh
        self.ticks_without_setpoint += fresh == 0
        plant.set_input(iq_ref_a=sp.iq_ref_a)
        plant.step(plant.sub_per_pwm)
        fb.seq = sp.seq
        fb.time_s = plant.output("time_s")
        fb.encoder_counts = plant.output("encoder_counts")
        fb.scale_counts = plant.output("scale_counts")
        fb.velocity_counts_s = plant.output("motor_vel") * self._counts_per_rad
        fb.iq_a = plant.output("iq_meas_a")
        self.feedbacks += ep.send_feedback(fb)

    def link(self) -> dict:
        """The counts since the last call (then zeroed): setpoints, feedbacks sent, ticks
        that found no new setpoint."""
        counts = {"setpoints": self.setpoints, "feedbacks": self.feedbacks,
                  "ticks_without_setpoint": self.ticks_without_setpoint}
        self.setpoints = self.feedbacks = self.ticks_without_setpoint = 0
        return counts


def adapter_step(stack: ExitStack, adapter: str, config: Path = PLANT_CONFIG
                 ) -> PlantOverAdapter:
    """The plant behind ``adapter``'s device end with its controller child running, both
    closed by ``stack``; warmed (compiled code and the link) before it is returned."""
    if adapter not in ADAPTERS:
        raise ValueError(f"adapter must be one of {ADAPTERS}, got {adapter!r}")
    ep = stack.enter_context(open_endpoint("udp://127.0.0.1:0", "device"))
    stack.enter_context(server(square_wave_controller, f"udp://127.0.0.1:{ep.address[1]}"))
    step = PlantOverAdapter(ep, config)
    for k in range(PLANT_WARMUP_CALLS):
        step(k)
        select.select((ep,), (), (), 0.01)  # the controller's answer, not a busy wait
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
        adapter: None, or one of :data:`ADAPTERS` (needs ``with_plant``): the plant is
            stepped behind that adapter's device end, a controller child on the other.
    """
    if any(not 1 <= r <= 1_000_000 for r in rates):
        raise ValueError(f"rates must be 1..1000000 Hz, got {rates}")
    if adapter is not None and not with_plant:
        raise ValueError(f"adapter={adapter!r} needs with_plant: the adapter carries the "
                         f"plant's setpoints and feedback")
    with ExitStack() as stack:
        linked = adapter_step(stack, adapter) if adapter is not None else None
        step = linked or (plant_step() if with_plant else _idle_step)
        cpu = last_cpu()
        rows = []
        for rate_hz in rates:
            row = {**bench_rate(rate_hz, seconds, step, cpu, note), "with_plant": with_plant,
                   "adapter": adapter, "link": None if linked is None else linked.link()}
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
