"""What a CAN frame costs on the wire (io_adapters.can_bus_time) and what a PDO
configuration asks of the bus.

References: the CRC-15/CAN check value of the CRC catalogue (poly 4599h, init 0: 059Eh for
ASCII "123456789"); a second, string-based bit stuffer written here (ISO 11898-1: after
five equal bits one of the opposite value, which counts in the next run); the worst-case
frame length of Davis, Burns, Bril and Lukkien (2007, eq. 4, with the 3-bit
intermission): 55 bits empty, 135 bits for eight bytes.
"""

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from io_adapters.can_bus_time import (
    TRAILER_BITS,
    _bits,
    _crc15,
    frame_bits,
    per_cycle,
    plan_cycle,
    worst_frame_bits,
)
from io_adapters.can_tap import CycleLoad


def stuffed_length(bits: str) -> int:
    """The length of ``bits`` after bit stuffing, by rewriting the string."""
    out, i = "", 0
    while i < len(bits):
        out += bits[i]
        i += 1
        if re.search(r"(00000|11111)$", out):
            out += "1" if out[-1] == "0" else "0"
    return len(out)


def reference_bits(can_id: int, data: bytes) -> int:
    head = "0" + format(can_id, "011b") + "000" + format(len(data), "04b")
    head += "".join(format(b, "08b") for b in data)
    crc = format(_crc15([int(c) for c in head]), "015b")
    return stuffed_length(head + crc) + TRAILER_BITS


def test_crc15_is_the_catalogues():
    bits = [b for byte in b"123456789" for b in _bits(byte, 8)]
    assert _crc15(bits) == 0x059E


def test_the_worst_case_bound_is_the_papers():
    assert [worst_frame_bits(n) for n in (0, 1, 4, 8)] == [55, 65, 95, 135]
    with pytest.raises(ValueError):
        worst_frame_bits(9)


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_frame_bits_counts_the_stuff_bits_as_sent(can_id, data):
    bits = frame_bits(can_id, data)
    assert bits == reference_bits(can_id, data)
    nominal = 47 + 8 * len(data)
    assert nominal <= bits <= worst_frame_bits(len(data))


def test_an_all_zero_frame_by_hand():
    """ID 0, DLC 0: SOF and 18 more zero bits, then the CRC of zeros (0): 34 zeros in a
    row, a stuff bit after every five of them (6), then the 13 unstuffed trailer bits."""
    assert frame_bits(0x000, b"") == 34 + 6 + 13


def test_a_plan_says_its_load():
    """The default mapping of one node at 1 ms and 1 Mbit/s: SYNC with its counter
    (1 byte), RPDO1 3 bytes, RPDO2 8, RPDO3 4, RPDO4 4, TPDO1 5, TPDO2 8, TPDO3 8 --
    850 bits at the worst, 85 % of the cycle."""
    sizes = [1, 3, 8, 4, 4, 5, 8, 8]
    plan = plan_cycle([(f"frame {k}", 1.0, n) for k, n in enumerate(sizes)], 1e-3, 1_000_000)
    assert plan.bits == 850 and plan.load == pytest.approx(0.85) and plan.fits
    half = plan_cycle([("heartbeat", 0.5, 1)], 1e-3, 125_000)
    assert half.bits == 32.5 and half.load == pytest.approx(32.5 / 125)
    assert not plan_cycle([("x", 1.0, 8)], 100e-6, 1_000_000).fits
    assert "85% of the bus" in plan.describe()


def test_per_cycle_is_the_frames_rate():
    """A frame counts at its rate: every cycle 1, every 0.4 ms 2.5 per 1 ms cycle, a
    heartbeat every 100 ms 0.01 (not a whole frame in every cycle), never 0."""
    assert per_cycle(1e-3, 1e-3) == 1 and per_cycle(0.4e-3, 1e-3) == pytest.approx(2.5)
    assert per_cycle(0.0, 1e-3) == 0.0 and per_cycle(100e-3, 1e-3) == pytest.approx(0.01)


def test_the_bus_room_fills_at_the_bit_rate_up_to_one_cycle():
    """CycleLoad's room, by hand at 1 Mbit/s and a 1 ms cycle (1000 bits): full at the
    first SYNC; 600 bits later 400 are left; 0.2 ms on, 600 again; never above 1000 however
    long the bus is idle.  A SYNC every 0.5 ms carries at most 500 bits per cycle: what is
    beyond counts in the next, and the busiest cycle's share stays at 1."""
    load = CycleLoad(bit_rate=1e6, capacity_bits=1000.0)
    load.close(10.0)
    assert load.room(1000, 10.0) and not load.room(1001, 10.0)
    load.add(600, 10.0)
    assert load.room(400, 10.0) and not load.room(401, 10.0)
    assert load.wait_s(600, 10.0) == pytest.approx(200e-6)
    assert load.room(599, 10.0002) and not load.room(601, 10.0002)
    assert not load.room(1001, 11.0)
    load.bits = 0
    load.close(11.0)
    load.add(800, 11.0)
    load.close(11.0005)
    assert load.bits == 300 and load.total_bits == 500
    assert load.max_share == pytest.approx(1.0) and load.max_share <= 1.0


def test_a_frame_taken_late_owes_the_room_its_bits_only_within_a_cycle():
    """A received frame whose arrival stamp is older than the room's last update takes its
    bits within one cycle of that update; one older than that leaves the room as it is
    (the room filled to its cap since), though it still counts in the cycle's load."""
    load = CycleLoad(bit_rate=1e6, capacity_bits=1000.0)
    load.close(10.0)
    assert load.room(1000, 10.01)
    load.add(100, 10.0095)
    assert load.credit_bits == 900
    load.add(100, 10.005)
    assert load.credit_bits == 900 and load.bits == 200


def test_a_flood_owes_the_room_one_cycle_at_most():
    """Frames stamped closer than the bit rate allows (a fuzzer on a virtual bus) leave the
    room at most one cycle in debt: a frame of ours waits two cycles at the most, as on a
    bus that had carried them."""
    load = CycleLoad(bit_rate=1e6, capacity_bits=1000.0)
    load.close(10.0)
    for _ in range(1000):
        load.add(135, 10.0)
    assert load.credit_bits == -1000.0
    assert load.wait_s(135, 10.0) == pytest.approx(1135e-6)
