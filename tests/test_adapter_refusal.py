"""Refused values and the handshake, one message at a time, over both msgpack transports
(the links of tests/test_adapters.py: real sockets on 127.0.0.1, a real pty pair).

:meth:`SetpointBounds.refusal` is checked against the field-by-field reference of
tests/test_adapter_decoders.py and at its bounds; then what a refusal does on the wire
(dropped whole, heard, named in ``refused_axes``), the handshake's rules (the pinned
peer's own HELLO, another session's before and after ``takeover_ms``, the controller's
repeated HELLO) and the small API around them.
"""

import math
import socket
import time

import msgpack
import pytest
from hypothesis import given

from io_adapters import AdapterConfigError, Feedback, Setpoint, codec, open_endpoint
from io_adapters.base import LINK_HEARTBEAT_LOST, LINK_RESET, LINK_STOPPED
from io_adapters.messages import (
    MODE_CSP,
    MODE_CST,
    REFUSED_MODE,
    REFUSED_NONFINITE,
    REFUSED_RANGE,
    SetpointBounds,
    message_pair,
)
from io_adapters.udp import UdpEndpoint
from tests.test_adapter_decoders import BOUNDS, WILD_AXIS, reference_refusal
from tests.test_adapters import (  # noqa: F401  (pytest fixtures)
    QUIET_S,
    WAIT_S,
    assert_counts_add_up,
    link,
    make_link,
    setpoint_msg,
)


@given(BOUNDS, WILD_AXIS)
def test_refusal_is_the_reference(bounds, axis):
    mode, floats = axis
    assert bounds.refusal(mode, *floats) == reference_refusal(mode, floats, bounds)


def test_bounds_are_inclusive_and_checked_in_order():
    b = SetpointBounds(current_a=10.0, modes=frozenset((MODE_CST,)))
    above = math.nextafter(10.0, math.inf)
    assert b.refusal(MODE_CST, 0.0, 0.0, 0.0, 10.0, -10.0, 0.0, 0.0) == 0
    assert b.refusal(MODE_CST, 0.0, 0.0, 0.0, 0.0, -above, 0.0, 0.0) == REFUSED_RANGE
    assert b.refusal(MODE_CSP, 0.0, 0.0, 0.0, above, 0.0, 0.0, 0.0) == REFUSED_MODE
    assert b.refusal(MODE_CSP, 0.0, 0.0, 0.0, above, 0.0, 0.0, -math.inf) == REFUSED_NONFINITE
    default = SetpointBounds()
    assert default.refusal(MODE_CSP, 2.0**53, -2.0**53, 2.0**53, 1e308, 0.0, 0.0, 0.0) == 0
    assert default.refusal(MODE_CSP, math.nextafter(2.0**53, math.inf), 0.0, 0.0, 0.0, 0.0,
                           0.0, 0.0) == REFUSED_RANGE
    assert default.refusal(-2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) == REFUSED_MODE


@pytest.mark.parametrize("kwargs, match", [
    ({"current_a": -1.0}, "current_a=-1.0"),
    ({"voltage_v": math.nan}, "voltage_v=nan"),
    ({"position_counts": "1e6"}, "position_counts='1e6'"),
    ({"modes": frozenset((MODE_CSP, "CSV"))}, "modes="),
])
def test_bad_bounds_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SetpointBounds(**kwargs)


def test_a_refused_setpoint_is_dropped_whole_and_still_heard(link):
    """A NaN in a field the mode does not use, a current beyond the bound, an unknown
    mode: each refused and counted once by its reason, the caller's record keeps the last
    good setpoint, and the next good one is taken with nothing lost."""
    device, ctl = link.device, link.controller
    device.setpoint_bounds = (SetpointBounds(current_a=5.0),)
    got = Setpoint()
    ctl.send_setpoint(Setpoint(mode=MODE_CSP, target_position_counts=100.0, iq_ref_a=1.0))
    assert device.recv_setpoint(got, WAIT_S) and device.refused_axes == 0
    kept = Setpoint(**{n: getattr(got, n) for n in Setpoint.__slots__})
    for bad in (Setpoint(mode=MODE_CSP, target_position_counts=200.0, ud_v=math.nan),
                Setpoint(mode=MODE_CSP, target_position_counts=200.0, iq_ref_a=-5.5),
                Setpoint(mode=7, target_position_counts=200.0)):
        ctl.send_setpoint(bad)
        assert not device.recv_setpoint(got, QUIET_S)
        assert device.refused_axes == 1 and got == kept
    ctl.send_setpoint(Setpoint(mode=MODE_CSP, target_position_counts=300.0, iq_ref_a=-5.0))
    assert device.recv_setpoint(got, WAIT_S) and device.refused_axes == 0
    assert got.target_position_counts == 300.0
    s = device.stats
    assert (s.refused_nonfinite, s.refused_mode, s.refused_range) == (1, 1, 1)
    assert (s.received, s.lost) == (2, 0)
    assert_counts_add_up(s, frames=6)  # and the HELLO


def test_a_group_names_every_refused_axis_and_is_counted_once(make_link):
    link = make_link()
    device, ctl = link.device, link.controller
    device.setpoint_bounds = (SetpointBounds(), SetpointBounds(modes=frozenset((MODE_CSP,))),
                              SetpointBounds(current_a=1.0))
    sp, got = message_pair(3)[0], message_pair(3)[0]
    for rec in sp.axes:
        rec.mode, rec.target_position_counts = MODE_CSP, 10.0
    ctl.send_setpoint(sp)
    assert device.recv_setpoint(got, WAIT_S)
    sp.axes[1].mode, sp.axes[2].iq_ref_a = MODE_CST, 2.0  # mode on axis 1, range on 2
    sp.axes[0].target_position_counts = 20.0
    ctl.send_setpoint(sp)
    assert not device.recv_setpoint(got, QUIET_S) and device.refused_axes == 0b110
    assert got.axes[0].target_position_counts == 10.0  # nothing of it reached the record
    sp.axes[1].mode, sp.axes[0].id_ref_a = MODE_CSP, math.inf  # non-finite on 0, range on 2
    ctl.send_setpoint(sp)
    assert not device.recv_setpoint(got, QUIET_S) and device.refused_axes == 0b101
    sp.axes[0].id_ref_a, sp.axes[2].iq_ref_a = 0.0, 1.0
    ctl.send_setpoint(sp)
    assert device.recv_setpoint(got, WAIT_S) and device.refused_axes == 0
    assert [r.target_position_counts for r in got.axes] == [20.0, 10.0, 10.0]
    s = device.stats  # counted once each, under the lowest code of its axes
    assert (s.refused_nonfinite, s.refused_mode, s.refused_range, s.lost) == (1, 1, 0, 0)
    assert_counts_add_up(s, frames=5)


def test_bounds_are_one_or_one_per_axis():
    with UdpEndpoint("device", ("127.0.0.1", 0)) as device:
        with pytest.raises(AdapterConfigError, match="one or more SetpointBounds"):
            device.setpoint_bounds = ()
        with pytest.raises(AdapterConfigError, match="one or more SetpointBounds"):
            device.setpoint_bounds = (SetpointBounds(), {"current_a": 1.0})
        device.setpoint_bounds = (SetpointBounds(), SetpointBounds())
        with UdpEndpoint("controller", device.address[:2]) as ctl:
            ctl.send_setpoint(Setpoint())
            with pytest.raises(AdapterConfigError, match="2 setpoint_bounds for a single-axis"):
                device.recv_setpoint(Setpoint(), WAIT_S)


def test_feedback_with_a_non_finite_value_is_refused(link):
    got = Feedback(encoder_counts=5.0)
    link.controller.send_setpoint(Setpoint())
    assert link.device.recv_setpoint(Setpoint(), WAIT_S)
    link.device.send_feedback(Feedback(encoder_counts=1.0, iq_a=math.nan))
    assert not link.controller.recv_feedback(got, QUIET_S) and got.encoder_counts == 5.0
    assert link.controller.stats.refused_nonfinite == 1
    assert_counts_add_up(link.controller.stats, frames=2)  # the WELCOME and the refused one


def test_msgpack_links_have_no_link_conditions(link):
    assert (LINK_HEARTBEAT_LOST, LINK_STOPPED, LINK_RESET) == (1, 2, 4)
    assert link.device.link_conditions(0) == 0


# -- the handshake, message by message -------------------------------------------------------

def test_the_pinned_peers_own_hello_is_welcomed_again(link):
    link.controller.send_setpoint(Setpoint(seq=1))
    assert link.device.recv_setpoint(Setpoint(), WAIT_S)
    link.inject([codec.encode_hello(link.session, 1)])  # the same session, as it repeats
    link.controller.send_setpoint(Setpoint(seq=2))
    got = Setpoint()
    assert link.device.recv_setpoint(got, WAIT_S) and got.seq == 2
    s = link.device.stats
    assert (s.handshakes, s.foreign, s.peer_restarts, s.lost) == (2, 0, 0, 0)


def test_another_session_gets_in_only_after_takeover_ms(make_link):
    """On the pinned peer's own address (UDP) or line (serial): a HELLO of another session
    is refused while the peer talks, and accepted once it has been silent for
    takeover_ms (10 ms here; the test waits 5 times that); the sequence check then starts
    at the HELLO's frame number, and the old session is stale."""
    link = make_link("?takeover_ms=10")
    device, ctl, new = link.device, link.controller, link.session ^ 0xFFFF
    ctl.send_setpoint(Setpoint(seq=1))
    link.inject([codec.encode_hello(new, 40)])
    got = Setpoint()
    assert device.recv_setpoint(got, WAIT_S) and got.seq == 1
    assert not device.recv_setpoint(got, QUIET_S)
    assert (device.stats.foreign, device.stats.peer_restarts) == (1, 0)
    time.sleep(0.05)
    link.inject([codec.encode_hello(new, 40), setpoint_msg(new, 40, seq=2)])
    ctl.send_setpoint(Setpoint(seq=3))  # the old session, now stale
    assert device.recv_setpoint(got, WAIT_S) and got.seq == 2
    assert not device.recv_setpoint(got, QUIET_S) and got.seq == 2
    s = device.stats
    assert (s.peer_restarts, s.handshakes, s.stale_session, s.lost) == (1, 2, 1, 0)
    assert_counts_add_up(s, frames=6)


def test_the_controller_repeats_its_hello_until_welcomed():
    """A raw device that does not answer at first: HELLOs come before setpoints, at most
    one per 100 ms (counted against the time the sends took); after a WELCOME accepted=0
    they go on, after accepted=1 they stop."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        raw.bind(("127.0.0.1", 0))
        raw.settimeout(WAIT_S)
        start = time.monotonic()
        with open_endpoint(f"udp://127.0.0.1:{raw.getsockname()[1]}", "controller") as ctl:
            sp = Setpoint()
            for k in range(40):
                sp.seq = k
                ctl.send_setpoint(sp)
                time.sleep(0.005)
            took_s = time.monotonic() - start
            kinds = []
            while kinds.count(codec.KIND_SETPOINT) < 40:
                message, where = raw.recvfrom(2048)
                kinds.append(msgpack.unpackb(message)[1])
            assert kinds[0] == codec.KIND_HELLO
            assert 1 <= kinds.count(codec.KIND_HELLO) <= 1 + took_s / 0.1
            for accepted in (0, 1):
                raw.sendto(codec.encode_welcome(9, 0, bool(accepted)), where)
                ctl.recv_feedback(Feedback(), QUIET_S)
                assert ctl.welcomed == bool(accepted)
            time.sleep(0.15)
            ctl.send_setpoint(sp)
            assert msgpack.unpackb(raw.recvfrom(2048)[0])[1] == codec.KIND_SETPOINT
            assert ctl.stats.handshakes == 2 and ctl.stats.received == 0


def test_exposed_says_whether_the_network_can_reach_it():
    with UdpEndpoint("device", ("127.0.0.1", 0)) as local:
        assert not local.exposed
    with open_endpoint("udp://0.0.0.0:0?allow_remote=1", "device") as anywhere:
        assert anywhere.exposed
    with open_endpoint("udp://127.0.0.1:0?peer=192.0.2.1:5005&allow_remote=1",
                       "device") as answering:
        assert answering.exposed


@pytest.mark.parametrize("option", ["takeover_ms=0", "takeover_ms=-5", "takeover_ms=inf",
                                    "takeover_ms=soon"])
def test_bad_takeover_is_refused(option):
    with pytest.raises(AdapterConfigError, match="takeover_ms"):
        open_endpoint(f"udp://127.0.0.1:0?{option}", "device")
