"""``hil controller``'s compiled loop (:mod:`hil.runtime.controller_steady`: one tick of
it, as :meth:`ControllerProcess.step` calls it) against the controller's Python tick, over
real UDP sockets on 127.0.0.1, bit for bit.

Two pairs, each an emulator (:class:`~hil.runtime.emulator.Emulator`, its Python tick)
and a controller process (:class:`~hil.runtime.controller_proc.ControllerProcess` on its
own UDP endpoint; one with the compiled loop, one without), tick by tick: the emulator's
tick answers the setpoint of the controller's tick before, then the controller's tick
reads that answer and sends the next setpoint.  Both run a part program from the enable
sequence to its end, with traffic mixed in: ticks the emulator skips (the controller
bridges the missing feedback at the drive's speed), two answers queued for one
controller tick (the newest taken), a stranger's datagram (foreign), a malformed one and a
repeated answer (both the Python path's to judge).  At the end the controllers' recorded
rows (all but the clock stamps), the setpoints the emulators received (their recordings,
all but the clock columns), every endpoint's counters and the controllers' states must
be the same; and the compiled loop must have run most ticks and declined each kind it
must, or the comparison would say nothing.
"""

import select
import socket
from dataclasses import fields

import pytest

from hil.runtime import controller_steady as CS
from hil.runtime import steady_tick as S
from hil.runtime.common import StopFlag
from hil.runtime.controller_proc import ControllerProcess, ControllerRunConfig
from hil.runtime.emulator import Emulator, RuntimeConfig
from io_adapters import open_endpoint
from io_adapters.messages import axis_records
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT

#: the records' clock stamps (each machine's own)
STAMPS = ("t_ns", "sp_t_ns", "sp_rx_ns", "tick_ns", "rx_ns")
#: the controller.npz integer columns that are clock stamps (compared for presence only)
STAMP_INTS = slice(3, 7)
#: the emulator recording's clock columns
CLOCK_COLUMNS = ("tick_start_ns", "sp_t_ns", "sp_rx_ns", "fb_t_ns", "lateness_ns",
                 "compute_ns")


class Pair:
    """An emulator and a controller process talking over UDP on 127.0.0.1, stepped by
    hand; ``extra`` maps a controller tick to the traffic around it."""

    def __init__(self, config, program, steady: bool, extra: dict):
        machine = load_machine_set(config)
        rc = RuntimeConfig(config, "udp://127.0.0.1:0", realtime=False)
        self.em = Emulator(rc, machine, log=lambda message: None)
        url = self.em.open()
        self.proc = ControllerProcess(ControllerRunConfig(config, url, program,
                                                          realtime=False), StopFlag())
        self.proc.ep = open_endpoint(url, "controller")
        self.proc.ep.drain = True
        self.proc.steady = CS.ControllerSteady.for_process(self.proc) if steady else None
        if self.proc.steady is not None:
            self.proc.steady.warm()
        self.stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.extra = extra
        self.k_em = 0
        # the handshake: the controller's HELLO, the emulator's WELCOME
        self._emulator_tick()
        self._wait(self.proc.ep)

    def close(self) -> None:
        self.proc.ep.close()
        self.em.endpoint.close()
        self.stranger.close()

    @staticmethod
    def _wait(ep) -> None:
        select.select((ep.fileno(),), (), (), 1.0)

    def _emulator_tick(self) -> None:
        self._wait(self.em.endpoint)
        self.em.step(self.k_em)
        self.em.recorder.end_tick(self.k_em, 0, 0)
        self.k_em += 1

    def tick(self, k: int) -> None:
        kind = self.extra.get(k)
        if kind != "skip":  # the drive's answer to the last setpoint
            self._emulator_tick()
        if kind == "queued":  # a second drive cycle before the controller reads
            self.proc.sp.seq = self.proc.sp.seq  # the setpoint the drive holds
            self.em.step(self.k_em)
            self.em.recorder.end_tick(self.k_em, 0, 0)
            self.k_em += 1
        ctl = self.proc.ep
        to = ctl._sock.getsockname()
        if kind == "stranger":
            self.stranger.sendto(b"\x01" + bytes(20), to)
        elif kind == "garbage":  # from the drive's own socket: malformed
            self.em.endpoint._sock.sendto(b"\x93\x01\x02", to)
        elif kind == "repeat":  # the drive's last answer again (same frame)
            self.em.endpoint._sock.sendto(self.em.endpoint.wire.encode(
                self.em.fb, self.em.endpoint.session, (self.em.endpoint._frame - 1)
                & 0xFFFFFFFF), to)
        if kind != "skip":
            self._wait(ctl)
            if kind in ("stranger", "garbage", "repeat", "queued"):
                select.select((), (), (), 0.002)
        self.proc.step(k)


def _run(config, program, extra, n_ticks):
    a, b = (Pair(config, program, steady, extra) for steady in (False, True))
    try:
        for k in range(n_ticks):
            a.tick(k)
            b.tick(k)
            if a.proc.rows == a.proc.n_run:
                break
        pa, pb = a.proc, b.proc
        assert pa.rows == pb.rows == pa.n_run, "the program did not finish"
        n = pa.rows
        assert pa.floats[:n].tobytes() == pb.floats[:n].tobytes()
        assert pa.ints[:n, :3].tobytes() == pb.ints[:n, :3].tobytes()
        assert ((pa.ints[:n, STAMP_INTS] != 0) == (pb.ints[:n, STAMP_INTS] != 0)).all()
        assert (pa.silent, pa.adapter_errors, pa.result) == (pb.silent, pb.adapter_errors,
                                                             pb.result)
        ra, rb = (p.em.recorder for p in (a, b))
        m = min(ra.committed, rb.committed)
        assert abs(ra.committed - rb.committed) <= 1
        cols_a, cols_b = ra.columns(0, m), rb.columns(0, m)
        for name, col in cols_a.items():
            if name not in CLOCK_COLUMNS:
                assert col.tobytes() == cols_b[name].tobytes(), name
        assert pa.ep.stats == pb.ep.stats
        for sa, sb in zip(axis_records(pa.sp), axis_records(pb.sp)):
            for f in fields(sa):
                if f.name != "t_ns":
                    assert getattr(sa, f.name) == getattr(sb, f.name), f.name
        for fa, fbb in zip((pa.fb, *axis_records(pa.fb)), (pb.fb, *axis_records(pb.fb))):
            for f in fields(fa):
                if f.name not in STAMPS + ("axes",):
                    assert getattr(fa, f.name) == getattr(fbb, f.name), f.name
        return b
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("config, program", [
    (CONFIGS / "arrow500_x.toml", ROOT / "programs" / "demo_moves.nc"),
    (CONFIGS / "machines" / "geiss_5axis.toml", ROOT / "programs" / "geiss_5axis_moves.nc"),
])
def test_the_compiled_controller_tick_is_the_python_tick(config, program):
    extra = {}
    for start in (3000, 6000, 9000):
        extra.update({start: "skip", start + 1: "skip", start + 50: "queued",
                      start + 100: "stranger", start + 150: "garbage", start + 200: "repeat"})
    b = _run(config, program, extra, 40_000)
    steady = b.proc.steady
    assert steady.ticks >= 0.8 * b.proc.n_run
    # the malformed and the repeated answer went to the Python path; the skipped ticks,
    # the queued answers and the stranger's datagram were taken compiled
    assert steady.declined.get(S.DECLINED_FRAME, 0) >= 3
    assert steady.declined.get(S.DECLINED_SEQUENCE, 0) >= 3
    assert b.proc.ep.stats.foreign == 3 and b.proc.ep.stats.drained >= 3
