"""The emulator's compiled loop as ``hil run``'s loop runs it (:mod:`hil.runtime.steady_tick`
through :func:`hil.rt.loop.run_ticks`' ``burst``): many ticks a call, each waited for,
answered and ended in compiled code, the overrun policy and the Python path's ticks
between the calls still the loop's.

The loop's discipline with a burst is checked on a simulated clock against what the
module docstring of :mod:`hil.rt.loop` says (a burst's ticks counted, the last one's
overrun judged by the policy, a tick woken in a burst and declined run at once without a
second wait).  The compiled loop itself runs against a controller in another process
(``hil bench tick``'s: the CiA 402 enable sequence, then CSP motion, one setpoint per
period of its own clock): every tick's row is in the ring in order, the books add up as
the endpoint's Python path keeps them, the feedback the controller last received is the
drive's last answer, and a stop requested from another thread ends the call at the next
tick.
"""

import multiprocessing
import threading

import numpy as np

from hil.bench.tick import START_S, controller
from hil.rt.clock import SimulatedClock
from hil.rt.loop import OverrunPolicy, RealTimeLoop
from hil.runtime import steady_tick as S
from hil.runtime.emulator import Emulator, RuntimeConfig
from plant.machines import load_machine_set
from tests.conftest import CONFIGS

P = 1000


class ScriptedBurst:
    """A burst that runs the ticks a script gives, on a simulated clock: each entry
    (ticks, overran, declined) runs that many ticks of ``cost_ns`` each, the last one
    (``overran``) 1.5 periods instead, then wakes the next one and declines it or not."""

    def __init__(self, loop, clock, script, cost_ns=100):
        self.loop, self.clock, self.script, self.cost_ns = loop, clock, list(script), cost_ns
        self.ran: list[int] = []
        self.woken: list[int] = []

    def __call__(self, k, t0, n):
        if not self.script:
            return 0, None, None
        ticks, overran, declined = self.script.pop(0)
        for i in range(ticks):
            self.clock.sleep_until(t0 + (k + i) * P)
            self.clock.advance(self.cost_ns if not (overran and i == ticks - 1) else 3 * P // 2)
            self.ran.append(k + i)
        end = self.clock.now_ns()
        if declined:
            self.woken.append(k + ticks)
            return ticks, end if ticks else None, self.clock.sleep_until(t0 + (k + ticks) * P)
        return ticks, end if ticks else None, None


def test_run_ticks_takes_a_bursts_ticks_and_judges_the_last():
    stepped = []
    clock = SimulatedClock(start_ns=0)
    loop = RealTimeLoop(P, stepped.append, n_ticks=40, clock=clock,
                        policy=OverrunPolicy("count"))
    loop.burst = burst = ScriptedBurst(loop, clock, [
        (10, False, False),   # ticks 0-9 compiled
        (5, False, True),     # 10-14 compiled, 15 woken and declined: Python runs it now
        (0, False, True),     # 16 woken and declined at once
        (4, True, False),     # 17-20, the last ends half a period after the next deadline
    ])
    stats = loop.run()
    assert burst.ran == list(range(10)) + list(range(10, 15)) + list(range(17, 21))
    assert burst.woken == [15, 16]
    # the declined ticks ran in Python without a second wait, as did every tick after the
    # script ran out
    assert stepped[:2] == [15, 16]
    assert stepped[2:] == list(range(21, 40))
    assert stats.ticks == 40 and stats.overruns == 1
    # the woken ticks' lateness is their wake-up's (0 on this clock), not a second wait's
    assert loop.lateness_ns[15] == 0 and loop.compute_ns[15] == 0


def test_a_bursts_overrun_stops_the_loop_under_the_stop_policy():
    clock = SimulatedClock(start_ns=0)
    loop = RealTimeLoop(P, lambda k: None, n_ticks=100, clock=clock,
                        policy=OverrunPolicy("stop", stop_after=1))
    loop.burst = ScriptedBurst(loop, clock, [(30, True, False)])
    stats = loop.run()
    assert stats.stopped_by == "overruns" and stats.ticks == 30


def _emulator(n_ticks: int) -> Emulator:
    config = CONFIGS / "arrow500_x.toml"
    rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False,
                       duration_s=n_ticks / 8000.0)
    emulator = Emulator(rc, load_machine_set(config), log=lambda message: None)
    emulator.open()
    return emulator


def _with_controller(emulator: Emulator, run):
    ctx = multiprocessing.get_context("spawn")
    parent, child_conn = ctx.Pipe()
    child = ctx.Process(target=controller, args=(emulator.endpoint.address[1], 1,
                                                  emulator.timing.period_ns, child_conn))
    child.start()
    try:
        assert parent.poll(START_S), "the controller process did not start"
        parent.recv()
        return run()
    finally:
        parent.send("stop")
        child.join(10.0)
        if child.is_alive():
            child.kill()
            child.join()
        emulator.endpoint.close()


def test_the_compiled_loop_runs_hil_runs_ticks():
    n = 6000  # 0.75 s at 8 kHz: the ring (1 s) holds every row
    emulator = _emulator(n)
    steady = emulator.steady
    assert emulator.loop.burst == steady.burst
    stats = _with_controller(emulator, emulator.loop.run)
    assert stats.stopped_by == "completed"
    rows = emulator.recorder.columns(0, emulator.recorder.committed)
    # every tick run has its row, in order, finished with the loop's figures
    assert stats.ticks + stats.skipped == n
    assert emulator.recorder.committed == stats.ticks
    assert (np.diff(rows["tick"]) >= 1).all() and rows["tick"][-1] == n - 1
    assert (rows["compute_ns"] > 0).all()
    # the drive enabled within the run and the compiled loop ran its steady ticks, many a
    # call
    enabled = rows["drive_state"] == 4
    assert enabled.sum() > n // 2
    assert steady.ticks >= enabled.sum() - 100
    assert steady.calls * 10 < steady.ticks
    # the books: every datagram read was counted as the endpoint's Python path counts it
    st = emulator.endpoint.stats
    assert st.frames == (st.received + st.malformed + st.refused_nonfinite + st.refused_mode
                         + st.refused_range + st.duplicates + st.out_of_order + st.foreign
                         + st.stale_session + st.handshakes + st.injections)
    assert st.received - st.drained == emulator.setpoints_heard == rows["sp_new"].sum()
    # every tick answered from the first setpoint on (the controller never fell silent)
    assert st.sent == stats.ticks - np.flatnonzero(rows["sp_new"])[0]
    # the records the Python path reads are the last compiled tick's
    assert emulator.fb.seq == rows["sp_seq"][-1]
    assert emulator.sp.target_position_counts == rows["sp_target_position_counts"][-1]


def test_a_stop_request_from_another_thread_ends_the_call_at_the_next_tick():
    """The call releases the GIL, so another thread's request is made while it runs,
    and it reads the request before every tick: the loop stops within a tick or two of
    it, not at the call's end (:data:`~hil.runtime.steady_tick.BURST_S`, 80 ticks)."""
    n = 40_000
    emulator = _emulator(n)
    requested_at = []

    def stop():
        requested_at.append(emulator.recorder.committed)
        emulator.loop.request_stop()

    def run():
        stopper = threading.Timer(0.5, stop)  # the ring holds 1 s
        stopper.start()
        try:
            return emulator.loop.run()
        finally:
            stopper.cancel()

    stats = _with_controller(emulator, run)
    assert stats.stopped_by == "stop_flag" and stats.ticks < n
    assert emulator.steady.ticks > 1000 and emulator.loop.stop_word[0] == 1
    assert stats.ticks - requested_at[0] <= 2
    assert S.BURST_S * emulator.timing.rate_hz >= 10  # so the bound above says something
