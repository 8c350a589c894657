"""The fixed binary wire (``wire=fixed``, :mod:`io_adapters.codec_fixed`): the C header is
its layout, records cross a real UDP link and a pty pair's serial frames whole, bad messages are refused and counted as on
the msgpack wire, and the emulator answers a fixed-wire controller with its home switch and
the index mark it passed.
"""

import math
import os
import shutil
import socket
import struct
import subprocess

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil.cia402 import EnableSequencer
from hil.runtime.emulator import Emulator
from hil.runtime.emulator_config import RuntimeConfig
from io_adapters import AdapterConfigError, codec, open_endpoint
from io_adapters import codec_fixed as F
from io_adapters.base import FrameError
from io_adapters.messages import (
    DI_HOME_SWITCH,
    MODE_CSP,
    MODE_CSV,
    MODE_VOLTAGE,
    Feedback,
    FeedbackGroup,
    InjectRequest,
    Setpoint,
    SetpointBounds,
    SetpointGroup,
    message_pair,
)
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT
from tests.test_adapter_decoders import FLOATS
from tests.test_adapters import QUIET_S, WAIT_S, assert_counts_add_up

SP_FLOATS = tuple(f.name for f in codec.SETPOINT_FIELDS if f.type is float)

HEADER = ROOT / "io_adapters" / "include" / "feeddrive_wire.h"
#: the C type each format code stands for, as the probe below names it
C_TYPES = {"B": "u8", "b": "i8", "H": "u16", "I": "u32", "i": "i32", "q": "i64",
           "d": "f64", "2s": "u8[2]"}


def _probe_source() -> str:
    """A C program printing ``struct field offset type`` for every field the codec knows,
    and ``struct - sizeof -``: it does not compile if the header lacks one."""
    lines = ["#include <stdio.h>", "#include <stddef.h>", f'#include "{HEADER}"',
             "#define T(x) _Generic((x), uint8_t: \"u8\", int8_t: \"i8\", uint16_t: \"u16\", "
             "uint32_t: \"u32\", int32_t: \"i32\", int64_t: \"i64\", double: \"f64\", "
             "uint8_t *: \"u8[2]\", default: \"?\")",
             "int main(void) {"]
    for name, fields in F.STRUCTS.items():
        lines.append(f'printf("{name} - %zu -\\n", sizeof(struct {name}));')
        for field, _ in fields:
            lines.append(f'printf("{name} {field} %zu %s\\n", '
                         f'offsetof(struct {name}, {field}), T(((struct {name} *)0)->{field}));')
    return "\n".join(lines + ["return 0; }"])


def test_the_c_header_is_the_codecs_layout(tmp_path):
    """Every struct and field of the codec is in the header at the codec's offset, with its
    type; each struct is as long as the codec's block (no field more, no padding)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc): .ci/test-deps installs gcc")
    src, exe = tmp_path / "probe.c", tmp_path / "probe"
    src.write_text(_probe_source())
    subprocess.run([cc, "-std=c11", "-Wall", "-Werror", "-o", exe, src], check=True,
                   capture_output=True, timeout=60)
    out = subprocess.run([exe], check=True, capture_output=True, text=True).stdout.split("\n")
    got = [line.split() for line in out if line]
    want = []
    for name, fields in F.STRUCTS.items():
        size = struct.calcsize("<" + "".join(code for _, code in fields))
        want.append([name, "-", str(size), "-"])
        want += [[name, field, str(at), C_TYPES[code]] for field, at, code in F.offsets(fields)]
    assert got == want


def _link(n_axes: int, device_query: str = "?wire=fixed"):
    device = open_endpoint(f"udp://127.0.0.1:0{device_query}", "device")
    device.setpoint_bounds = (SetpointBounds(),)
    ctl = open_endpoint(f"udp://127.0.0.1:{device.address[1]}?wire=fixed", "controller")
    return device, ctl


def _serial_link():
    """A fixed-wire serial link over a pty pair, the device on the master side."""
    master, slave = os.openpty()
    device = open_endpoint(f"serial://fd/{master}?wire=fixed", "device")
    device.setpoint_bounds = (SetpointBounds(),)
    return device, open_endpoint(f"serial://fd/{slave}?wire=fixed", "controller")


@pytest.mark.parametrize("transport, n_axes", [("udp", 1), ("udp", 3), ("serial", 1),
                                               ("serial", 2)])
def test_records_cross_a_link_whole(transport, n_axes):
    """Every field of a setpoint and of a feedback (the digital inputs and the index mark
    too) arrives as sent, on one axis (the plain records) and on several (groups), over
    UDP and in serial frames (two axes at most there: the feedback of three, 256 bytes,
    does not fit a frame)."""
    device, ctl = _link(n_axes) if transport == "udp" else _serial_link()
    with device, ctl:
        sp, fb = message_pair(n_axes)
        got_sp, got_fb = message_pair(n_axes)
        sp.seq = 0xFFFFFFFF
        for i, rec in enumerate(sp.axes if n_axes > 1 else (sp,)):
            rec.controlword, rec.mode = 0x001F + i, (MODE_CSP, MODE_CSV, MODE_VOLTAGE)[i]
            (rec.target_position_counts, rec.target_velocity_counts_s,
             rec.velocity_offset_counts_s, rec.iq_ref_a, rec.id_ref_a, rec.ud_v,
             rec.uq_v) = (-2.0**53 + i, 1.5, -0.0, 5e-324, 1.2345678901234567, -3.0, 7.0 * i)
        assert ctl.send_setpoint(sp) and device.recv_setpoint(got_sp, WAIT_S)
        sent = sp.axes if n_axes > 1 else (sp,)
        for a, b in zip(sent, got_sp.axes if n_axes > 1 else (got_sp,)):
            for name in Setpoint.__slots__:
                if name not in ("rx_ns", "t_ns", "seq"):  # seq: the message's (below)
                    assert repr(getattr(a, name)) == repr(getattr(b, name)), name
        assert got_sp.t_ns == sp.t_ns > 0 and got_sp.seq == 0xFFFFFFFF
        fb.seq, fb.time_s = 12, 3.25
        for i, rec in enumerate(fb.axes if n_axes > 1 else (fb,)):
            (rec.statusword, rec.fault, rec.digital_inputs, rec.index_marks,
             rec.index_counts) = (0x1237, -0x8611 * i, DI_HOME_SWITCH, -3 + i, 4194304.0 * i)
            (rec.encoder_counts, rec.scale_counts, rec.velocity_counts_s, rec.iq_a,
             rec.id_a) = (1e15 + i, -2.5, 1e-300, -0.0, 28.0)
        assert device.send_feedback(fb) and ctl.recv_feedback(got_fb, WAIT_S)
        for a, b in zip(fb.axes if n_axes > 1 else (fb,),
                        got_fb.axes if n_axes > 1 else (got_fb,)):
            for name in Feedback.__slots__:
                if name not in ("rx_ns", "t_ns", "sp_t_ns", "sp_rx_ns", "tick_ns", "seq",
                                "time_s"):
                    assert repr(getattr(a, name)) == repr(getattr(b, name)), name
        assert (got_fb.seq, got_fb.time_s) == (12, 3.25)
        assert got_fb.sp_t_ns == sp.t_ns and got_fb.t_ns >= got_fb.sp_rx_ns > 0
        for s in (device.stats, ctl.stats):
            assert (s.received, s.malformed, s.lost) == (1, 0, 0)


U32 = st.integers(0, 2**32 - 1)
STAMP = st.integers(0, 2**63 - 1)


@st.composite
def records(draw):
    """A setpoint and a feedback of 1 to 4 axes with every field drawn over its range."""
    n = draw(st.integers(1, 4))
    sp, fb = message_pair(n)
    for rec in (sp.axes if n > 1 else (sp,)):
        rec.controlword, rec.mode = draw(st.integers(0, 0xFFFF)), draw(st.integers(-128, 127))
        for name in SP_FLOATS:
            setattr(rec, name, draw(FLOATS))
    for rec in (fb.axes if n > 1 else (fb,)):
        rec.statusword, rec.fault = draw(st.integers(0, 0xFFFF)), draw(
            st.integers(-2**31, 2**31 - 1))
        rec.digital_inputs, rec.index_marks = draw(st.integers(0, 0xFFFF)), draw(
            st.integers(-2**31, 2**31 - 1))
        for name in ("encoder_counts", "scale_counts", "velocity_counts_s", "iq_a", "id_a",
                     "index_counts"):
            setattr(rec, name, draw(FLOATS))
    sp.seq, sp.t_ns = draw(U32), draw(STAMP)
    fb.seq, fb.time_s = draw(U32), draw(FLOATS)
    fb.sp_t_ns, fb.sp_rx_ns, fb.t_ns, fb.tick_ns = (draw(STAMP) for _ in range(4))
    return n, sp, fb, draw(U32), draw(U32)


def _strip(values: tuple, group: bool) -> tuple:
    """A decoded feedback without the extras the fixed wire adds."""
    if group:
        return values[:-1] + (tuple(a[:-3] for a in values[-1]),)
    return values[:-3]


@given(records())
def test_the_decoded_form_is_the_msgpack_wires(drawn):
    """Whatever the values, the fixed wire decodes a record into the msgpack wire's array
    of it (the feedback's extras after it; the version number is each wire's own), so the
    endpoint judges both alike."""
    n, sp, fb, session, frame = drawn
    for rec in (sp, fb):
        got = F.decode(F.encode(rec, session, frame), type(rec), n)
        want = codec.decode(codec.encode(rec, session, frame), type(rec), n)
        if rec is fb:
            extras = [a[-3:] for a in got[-1]] if n > 1 else [got[-3:]]
            assert repr(extras) == repr([(a.digital_inputs, a.index_marks, a.index_counts)
                                         for a in (fb.axes if n > 1 else (fb,))])
            got = _strip(got, n > 1)
        assert repr(got[1:]) == repr(want[1:])  # [0]: each wire's own version number


def _setpoint_bytes(frame: int, session: int, **values) -> bytearray:
    return bytearray(F.encode(Setpoint(mode=MODE_CSP, **values), session, frame))


#: (what, how a good one-axis setpoint's bytes are changed): each malformed
BAD = [
    ("one byte short", lambda b: b[:-1]),
    ("one byte long", lambda b: b + b"\0"),
    ("the header only", lambda b: b[:16]),
    ("shorter than a header", lambda b: b[:15]),
    ("bad magic", lambda b: b"FX" + b[2:]),
    ("version 2", lambda b: b[:2] + b"\x02" + b[3:]),
    ("kind 7", lambda b: b[:3] + b"\x07" + b[4:]),
    ("kind 2 (feedback) to a device", lambda b: b[:3] + b"\x02" + b[4:]),
    ("an INJECT", lambda b: b[:3] + b"\x05" + b[4:]),
    ("2 axes to a 1-axis device", lambda b: b[:12] + struct.pack("<H", 2) + b[14:]),
    ("accepted set", lambda b: b[:14] + b"\x01\x00" + b[16:]),
    ("reserved after seq", lambda b: b[:20] + b"\x01" + b[21:]),
    ("reserved in the axis", lambda b: b[:35] + b"\x01" + b[36:]),
    ("a negative t_ns", lambda b: b[:24] + struct.pack("<q", -1) + b[32:]),
    ("a msgpack message", lambda b: bytearray(b"\x93\x01\x02\x03")),
]


def test_bad_messages_are_refused_and_counted():
    """Each malformed message is counted once and dropped; bad values (NaN, a mode the
    drive does not take, a value beyond its bound) are refused by reason; the good
    setpoint after them is taken with nothing lost."""
    device, ctl = _link(1)
    raw = socket.socket(fileno=ctl.fileno())  # the controller's own address
    with device, ctl:
        device.setpoint_bounds = (SetpointBounds(current_a=5.0),)
        got, frame = Setpoint(), 0
        raw.sendto(_setpoint_bytes(frame, ctl.session, target_position_counts=1.0),
                   device.address)
        assert device.recv_setpoint(got, WAIT_S) and got.target_position_counts == 1.0
        for what, change in BAD:  # each under the next frame number, never taken
            raw.sendto(bytes(change(_setpoint_bytes(frame + 1, ctl.session))),
                       device.address)
            assert not device.recv_setpoint(got, QUIET_S), what
            assert device.stats.malformed == BAD.index((what, change)) + 1, what
        for values in ({"iq_ref_a": math.nan}, {"target_position_counts": math.inf},
                       {"iq_ref_a": 6.0}):
            frame += 1
            raw.sendto(_setpoint_bytes(frame, ctl.session, **values), device.address)
            assert not device.recv_setpoint(got, QUIET_S), values
        frame += 1
        bad_mode = bytearray(_setpoint_bytes(frame, ctl.session))
        bad_mode[34] = 7  # the axis's mode: 7 (interpolated position) is not taken
        raw.sendto(bytes(bad_mode), device.address)
        assert not device.recv_setpoint(got, QUIET_S)
        frame += 1
        raw.sendto(_setpoint_bytes(frame, ctl.session, target_position_counts=2.0),
                   device.address)
        assert device.recv_setpoint(got, WAIT_S) and got.target_position_counts == 2.0
        s = device.stats
        assert (s.refused_nonfinite, s.refused_mode, s.refused_range) == (2, 1, 1)
        assert (s.malformed, s.received, s.lost) == (len(BAD), 2, 0)
        assert_counts_add_up(s)
    raw.detach()


def test_inject_and_oversized_groups_are_not_carried():
    """The fixed wire has no INJECT (a fault goes on the msgpack wire, CAN or ``hil run
    --inject``) and at most 64 axes: both refused before anything is sent."""
    device, ctl = _link(1)
    with device, ctl:
        with pytest.raises(FrameError, match="carries no INJECT"):
            ctl.send_injection(InjectRequest(0, "friction_growth", {"growth_pct": 5.0}))
        with pytest.raises(FrameError, match="65 axes"):
            ctl.send_setpoint(SetpointGroup(tuple(Setpoint() for _ in range(65))))
        with pytest.raises(FrameError, match=r"axes\[1\]\.controlword=65536"):
            ctl.send_setpoint(SetpointGroup((Setpoint(), Setpoint(controlword=0x10000))))
        with pytest.raises(FrameError, match=r"axes\[1\]\.index_marks=2147483648"):
            device.send_feedback(FeedbackGroup((Feedback(), Feedback(index_marks=2**31))))
        assert ctl.stats.bytes_sent == 16  # the HELLO only


def test_an_unknown_wire_is_refused():
    with pytest.raises(AdapterConfigError, match="unknown wire 'cbor'; known: fixed, msgpack"):
        open_endpoint("udp://127.0.0.1:0?wire=cbor", "device")


def test_a_msgpack_controller_is_not_taken_by_a_fixed_device():
    """The two wires do not mix: each side counts the other's messages as malformed."""
    device = open_endpoint("udp://127.0.0.1:0?wire=fixed", "device")
    ctl = open_endpoint(f"udp://127.0.0.1:{device.address[1]}", "controller")
    with device, ctl:
        ctl.send_setpoint(Setpoint())
        assert not device.recv_setpoint(Setpoint(), QUIET_S)
        assert device.stats.received == 0 and device.stats.malformed == 2  # HELLO, setpoint


# -- the emulator over the fixed wire -----------------------------------------------------

ARROW = CONFIGS / "arrow500_x.toml"


def test_the_emulator_answers_with_its_home_switch_and_the_index_mark_passed(tmp_path):
    """An emulator on ``wire=fixed`` runs every tick in Python (the compiled tick reads
    msgpack only) and answers a fixed-wire controller: the home switch (60FDh bit 2) is on
    below its edge at 5 mm, and moving across a mark the feedback names that mark's count
    exactly, up and down (the mark at 10 mm: one motor revolution of the 10 mm lead)."""
    machine = load_machine_set(ARROW)
    rc = RuntimeConfig(ARROW, "udp://127.0.0.1:0?wire=fixed", run_dir=tmp_path / "run",
                       realtime=False, start_cnc=9.95)
    emulator = Emulator(rc, machine, log=lambda line: None)
    emulator.open()
    assert emulator.steady is None
    ctl = open_endpoint(f"udp://127.0.0.1:{emulator.endpoint.address[1]}?wire=fixed",
                        "controller")
    per_mm = emulator.drives[0].plant.counts_per_mark / 10.0
    sp, fb = Setpoint(mode=MODE_CSP), Feedback()
    seq = EnableSequencer(timeout_cycles=400)
    seq.enable()
    seen = []

    def tick(k: int) -> None:
        sp.seq = k
        ctl.send_setpoint(sp)
        emulator.step(k)
        emulator.recorder.end_tick(k, 0, 0)
        assert ctl.recv_feedback(fb, WAIT_S), f"tick {k}: no answer"
        seen.append((fb.encoder_counts, fb.index_marks, fb.index_counts, fb.digital_inputs))

    try:
        k = 0
        while not seq.done:
            sp.controlword = seq.next_controlword(fb.statusword)
            sp.target_position_counts = fb.encoder_counts
            tick(k)
            k += 1
            assert k < 400, seq.reason
        assert fb.digital_inputs == 0 and fb.index_marks == 0  # 9.95 mm: off the switch
        # CSP with the speed feed-forward: up 0.1 mm across the mark at 10 mm at 8 mm/s and
        # back, then down to 4.5 mm at 100 mm/s
        path = [*(9.95 + 0.001 * i for i in range(101)),
                *(10.05 - 0.001 * i for i in range(101)),
                *(9.95 - 0.0125 * i for i in range(437)), *[4.5] * 100]
        for target_mm, next_mm in zip(path, path[1:] + path[-1:]):
            sp.target_position_counts = target_mm * per_mm
            sp.velocity_offset_counts_s = (next_mm - target_mm) * per_mm * 8000.0
            tick(k)
            k += 1
        assert fb.fault == 0 and fb.encoder_counts / per_mm < 4.8, fb  # on the switch
        mark = 4194304.0
        changes = [(a, b) for a, b in zip(seen, seen[1:]) if a[1] != b[1]]
        assert [b[1] for _, b in changes] == [1, 0]  # up over the mark, then back down
        for a, b in changes:
            assert b[2] == mark and min(a[0], b[0]) < mark <= max(a[0], b[0])
        edges = [b for a, b in zip(seen, seen[1:]) if a[3] != b[3]]
        assert [e[3] for e in edges] == [DI_HOME_SWITCH]
        assert abs(edges[0][0] / per_mm - 5.0) < 0.02  # the switch's edge, in mm
    finally:
        ctl.close()
        emulator.endpoint.close()
