"""``hil bench adapters``: the setpoint-to-feedback round trip of each adapter against a
raw echo over the same transport, measured in the same run.

For each transport two servers run, each in a child process (``multiprocessing``,
spawn), and this process plays the controller:

* **adapter**: the child opens the device end with :func:`io_adapters.open_endpoint` and
  answers each :class:`~io_adapters.Setpoint` with a :class:`~io_adapters.Feedback`; here
  ``send_setpoint`` then ``recv_feedback``, and the round trip is ``fb.rx_ns - sp.t_ns``
  (this clock: setpoint stamped before encoding, feedback after decoding, the device's
  decode and encode included; what a controller sees);
* **raw echo**: the child reads bytes of the encoded setpoint's size (on serial: the
  framed size) and writes back as many as an encoded feedback has; here a clock read,
  the write, the read of the answer, a clock read.  No codec, no :class:`~io_adapters.Endpoint`.

Both children wait in ``select`` on their transport and their control pipe, so the two
differ only by what the adapter adds: codec, framing, checks and bookkeeping.  After
``WARMUP`` round trips each, the two alternate in blocks of ``BLOCK``, so that a drift
of the machine (another load, a VM's steal time) hits both alike.  ``/dev/cpu_dma_latency``
is held at 0 while measuring, as ``hil run`` does (the row says if that was granted):
without it idle-state exits add tens of µs to every wake-up on both sides.

Transports: ``udp`` — 127.0.0.1, ephemeral ports; ``serial`` — a socat pty pair (two
named ptys joined by ``socat``) when socat is installed (``apt-get install socat``), else
an ``os.openpty`` pair; this process holds its end as a descriptor (``serial://fd/N``), the
child opens the other by path.

Each row::

    {"adapter", "transport", "n", "setpoint_bytes", "feedback_bytes",
     "round_trip_us": {"p50", "p99", "p999", "max"}, "raw_echo_us": {...},
     "overhead_p50_us", "ratio_p50", "cpu_dma_latency_held"}

``overhead_p50_us`` is the difference of the two p50s, ``ratio_p50`` their ratio.
Percentiles are nearest rank (:class:`hil.rt.loop.Percentiles`).  The goal: UDP
``overhead_p50_us`` <= 30.
"""

import multiprocessing
import os
import select
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil.rt.loop import Percentiles
from hil.rt.scheduling import SchedulingRequest, realtime_scheduling
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.codec import U32, encode
from io_adapters.messages import MODE_CSP
from io_adapters.serial_link import frame

#: round trips of each kind before measuring; then blocks of BLOCK alternate
WARMUP = 200
BLOCK = 100
#: longest wait for an answer, for socat's ptys or for a child to stop (s)
WAIT_S = 5.0
#: longest wait for a child to start (imports, and a cold disk) (s)
START_S = 60.0
READ_CHUNK = 4096
#: only /dev/cpu_dma_latency; the rest of a real-time request stays off
DMA_LATENCY_ONLY = SchedulingRequest(fifo_priority=None, cpus=None, lock_memory=False,
                                     cpu_dma_latency_us=0, timer_slack_ns=None,
                                     freeze_gc=False)


class AdapterBenchError(RuntimeError):
    """A child did not start, or an answer did not come (or was not the one asked for)."""


def _setpoint() -> Setpoint:
    return Setpoint(controlword=0x000F, mode=MODE_CSP, target_position_counts=123456.789,
                    velocity_offset_counts_s=2048.5, iq_ref_a=0.75)


def _answer(sp: Setpoint, fb: Feedback) -> None:
    """The child's feedback: the setpoint's values echoed into a drive's fields."""
    fb.seq = sp.seq
    fb.statusword = 0x0637
    fb.encoder_counts = sp.target_position_counts
    fb.velocity_counts_s = sp.velocity_offset_counts_s
    fb.iq_a = sp.iq_ref_a


def message_sizes(serial: bool) -> tuple[int, int]:
    """Bytes of an encoded setpoint and feedback as the adapters send them (32-bit session,
    64-bit timestamps, counters at 0: the frame and sequence counters add a few bytes as
    they grow); framed on serial."""
    now, sp, fb = time.monotonic_ns(), _setpoint(), Feedback()
    sp.t_ns = fb.t_ns = fb.sp_t_ns = fb.sp_rx_ns = now
    _answer(sp, fb)
    wrap = frame if serial else bytes
    return len(wrap(encode(sp, U32, 0))), len(wrap(encode(fb, U32, 0)))


# -- the children ----------------------------------------------------------------------------

def _serve_adapter(url: str, conn) -> None:
    with open_endpoint(url, "device") as ep:
        conn.send(ep.address[1] if url.startswith("udp:") else None)
        sp, fb = Setpoint(), Feedback()
        while conn not in select.select((ep, conn), (), ())[0]:
            while ep.recv_setpoint(sp, 0):
                _answer(sp, fb)
                ep.send_feedback(fb)


def _serve_raw_udp(reply: bytes, conn) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        conn.send(sock.getsockname()[1])
        buf = bytearray(READ_CHUNK)
        while conn not in select.select((sock, conn), (), ())[0]:
            _, addr = sock.recvfrom_into(buf)
            sock.sendto(reply, addr)


def _serve_raw_serial(path: str, request_bytes: int, reply: bytes, conn) -> None:
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        conn.send(None)
        pending = 0
        while conn not in select.select((fd, conn), (), ())[0]:
            pending += len(os.read(fd, READ_CHUNK))
            while pending >= request_bytes:
                os.write(fd, reply)
                pending -= request_bytes
    finally:
        os.close(fd)


@contextmanager
def server(serve: Callable, *args) -> Iterator[object]:
    """Start ``serve(*args, conn)`` in a spawned process; yields what it sends once ready
    (a UDP port, or None); on exit asks it to stop and waits for it."""
    kind = serve.__name__
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    proc = ctx.Process(target=serve, args=(*args, there), daemon=True)
    proc.start()
    there.close()
    try:
        if not here.poll(START_S):
            raise AdapterBenchError(f"{kind} server did not start in {START_S} s")
        try:
            ready = here.recv()
        except EOFError as e:  # it died; its traceback is on stderr
            proc.join(WAIT_S)
            raise AdapterBenchError(f"{kind} server exited while starting "
                                    f"(exit code {proc.exitcode})") from e
        yield ready
    finally:
        try:
            here.send("stop")
        except OSError:  # it has gone already
            pass
        proc.join(WAIT_S)
        if proc.is_alive():
            proc.terminate()
            proc.join()
        here.close()


# -- the transports --------------------------------------------------------------------------

def _raw_mode(fd: int) -> int:
    tty.setraw(fd)
    return fd


@contextmanager
def _pty_pair() -> Iterator[tuple[str, int, str]]:
    """(description, a raw descriptor of this side, the path of the child's side) of a pty
    pair; the caller owns the descriptor (closes it, or hands it to an endpoint)."""
    if shutil.which("socat") is None:
        master, slave = os.openpty()
        try:
            yield "os.openpty pair", _raw_mode(master), os.ttyname(slave)
        finally:
            os.close(slave)
        return
    with tempfile.TemporaryDirectory(prefix="bench-pty-") as tmp:
        a, b = Path(tmp) / "a", Path(tmp) / "b"
        proc = subprocess.Popen(["socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + WAIT_S
            while not (a.exists() and b.exists()):
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise AdapterBenchError(f"socat made no pty pair (exit code {proc.poll()})")
                time.sleep(0.01)
            yield "socat pty pair", _raw_mode(os.open(a, os.O_RDWR | os.O_NOCTTY)), str(b)
        finally:
            proc.terminate()
            proc.wait()


@dataclass
class _Pair:
    """The two round trips of one transport, each filling an array of ns."""
    transport: str
    adapter: Callable[[np.ndarray], None]
    raw: Callable[[np.ndarray], None]


def _adapter_round_trips(url: str, stack: ExitStack) -> Callable[[np.ndarray], None]:
    ep = stack.enter_context(open_endpoint(url, "controller"))
    sp, fb = _setpoint(), Feedback()

    def run(out_ns: np.ndarray) -> None:
        for i in range(out_ns.size):
            sp.seq = (sp.seq + 1) & U32
            ep.send_setpoint(sp)
            if not ep.recv_feedback(fb, WAIT_S) or fb.seq != sp.seq:
                raise AdapterBenchError(f"{url}: no feedback to setpoint {sp.seq} in {WAIT_S} s "
                                        f"(last seq {fb.seq})")
            out_ns[i] = fb.rx_ns - sp.t_ns
    return run


def _udp(stack: ExitStack, request_bytes: int, reply_bytes: int) -> _Pair:
    device_port = stack.enter_context(server(_serve_adapter, "udp://127.0.0.1:0"))
    echo_port = stack.enter_context(server(_serve_raw_udp, bytes(reply_bytes)))
    sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    sock.bind(("127.0.0.1", 0))
    sock.connect(("127.0.0.1", echo_port))
    sock.settimeout(WAIT_S)
    request, buf = bytes(request_bytes), bytearray(READ_CHUNK)

    def raw(out_ns: np.ndarray) -> None:
        now = time.monotonic_ns
        for i in range(out_ns.size):
            t0 = now()
            sock.send(request)
            sock.recv_into(buf)  # socket.timeout (an OSError) after WAIT_S
            out_ns[i] = now() - t0
    return _Pair("127.0.0.1 datagrams",
                 _adapter_round_trips(f"udp://127.0.0.1:{device_port}", stack), raw)


def _serial(stack: ExitStack, request_bytes: int, reply_bytes: int) -> _Pair:
    kind, adapter_fd, adapter_there = stack.enter_context(_pty_pair())
    adapter = _adapter_round_trips(f"serial://fd/{adapter_fd}", stack)  # owns adapter_fd
    _, fd, raw_there = stack.enter_context(_pty_pair())
    stack.callback(os.close, fd)
    stack.enter_context(server(_serve_adapter, f"serial://{adapter_there}"))
    stack.enter_context(server(_serve_raw_serial, raw_there, request_bytes, bytes(reply_bytes)))
    request = bytes(request_bytes)

    def raw(out_ns: np.ndarray) -> None:
        now = time.monotonic_ns
        for i in range(out_ns.size):
            t0 = now()
            os.write(fd, request)
            got = 0
            while got < reply_bytes:
                if not select.select((fd,), (), (), WAIT_S)[0]:
                    raise AdapterBenchError(f"raw serial echo: no answer in {WAIT_S} s")
                got += len(os.read(fd, READ_CHUNK))
            out_ns[i] = now() - t0
    return _Pair(kind, adapter, raw)


TRANSPORTS = {"udp": _udp, "serial": _serial}


def bench_adapter(name: str, n: int) -> dict:
    """One row (see the module docstring): ``n`` round trips of each kind over ``name``."""
    request_bytes, reply_bytes = message_sizes(serial=name == "serial")
    with ExitStack() as stack:
        pair = TRANSPORTS[name](stack, request_bytes, reply_bytes)
        adapter_ns, raw_ns = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
        warm = np.empty(WARMUP, dtype=np.int64)
        with realtime_scheduling(DMA_LATENCY_ONLY) as granted:
            pair.adapter(warm)
            pair.raw(warm)
            for start in range(0, n, BLOCK):
                block = slice(start, min(start + BLOCK, n))
                pair.adapter(adapter_ns[block])
                pair.raw(raw_ns[block])
    adapter_us, raw_us = Percentiles.of_ns_in_us(adapter_ns), Percentiles.of_ns_in_us(raw_ns)
    return {"adapter": name, "transport": pair.transport, "n": n,
            "setpoint_bytes": request_bytes, "feedback_bytes": reply_bytes,
            "round_trip_us": adapter_us.as_dict(), "raw_echo_us": raw_us.as_dict(),
            "overhead_p50_us": adapter_us.p50 - raw_us.p50,
            "ratio_p50": adapter_us.p50 / raw_us.p50 if raw_us.p50 > 0 else None,
            "cpu_dma_latency_held": granted.cpu_dma_latency.granted}


def run(n: int, adapters: list[str],
        note: Callable[[str], None] = lambda message: None) -> list[dict]:
    """Benchmark every adapter in ``adapters`` ("udp", "serial") with ``n`` round trips of
    each kind; returns the JSON-ready rows.  ``note`` receives a line per adapter."""
    unknown = sorted(set(adapters) - set(TRANSPORTS))
    if unknown or n < 1:
        raise ValueError(f"adapters must be among {sorted(TRANSPORTS)} and n >= 1, "
                         f"got {adapters} and n={n}")
    rows = []
    for name in adapters:
        row = bench_adapter(name, n)
        rows.append(row)
        rt, raw = row["round_trip_us"], row["raw_echo_us"]
        note(f"  {name:<7} ({row['transport']})  round trip p50 {rt['p50']:7.1f} µs  "
             f"p99.9 {rt['p999']:7.1f}  raw echo p50 {raw['p50']:7.1f}  "
             f"p99.9 {raw['p999']:7.1f}  overhead p50 {row['overhead_p50_us']:+6.1f} µs")
    return rows


def main_rows(n: int, adapters: list[str]) -> list[dict]:
    """What ``hil bench adapters`` prints: :func:`run` with its notes on stderr."""
    return run(n, adapters, note=lambda message: print(message, file=sys.stderr, flush=True))
