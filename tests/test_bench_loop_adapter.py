"""``hil bench loop --with-plant --adapter udp`` (issue 12 part 8): the plant behind the UDP
adapter's device end in the real-time loop, a controller child on the other end.

Timing figures are not asserted (wall clock); what went over the link is: every tick
sends one feedback, the setpoints are the controller's answers to them, and a setpoint
reaches the plant (its sequence number comes back, its current drives the axis).
"""

import select

import pytest

from hil.bench import loop as bench_loop
from io_adapters import Feedback, Setpoint, open_endpoint
from io_adapters.messages import MODE_CST


def test_loop_with_plant_over_udp_counts_the_link(monkeypatch, tmp_path):
    """2 kHz for 0.2 s (cyclictest kept off PATH: its column is null): one feedback per
    tick, the controller's setpoints answering them, the child reaped."""
    monkeypatch.setenv("PATH", str(tmp_path))
    rows = bench_loop.run([2000], 0.2, with_plant=True, adapter="udp")
    (row,) = rows
    assert row["adapter"] == "udp" and row["with_plant"] is True
    link = row["link"]
    assert link["feedbacks"] == row["ticks"] > 0
    assert 0 < link["setpoints"] <= link["feedbacks"] + 1
    assert 0 <= link["ticks_without_setpoint"] <= row["ticks"]
    assert row["cyclictest_us"] is None


def test_adapter_tick_applies_the_setpoint_and_answers_it():
    """One tick by hand, this process playing the controller: the feedback carries the
    setpoint's sequence number and one PWM period of plant time, and a held +2 A setpoint
    turns the motor forward (encoder counts grow)."""
    with open_endpoint("udp://127.0.0.1:0", "device") as ep, \
            open_endpoint(f"udp://127.0.0.1:{ep.address[1]}", "controller") as ctl:
        step = bench_loop.PlantOverAdapter(ep)
        sp, fb = Setpoint(seq=7, controlword=0x000F, mode=MODE_CST, iq_ref_a=2.0), Feedback()
        assert ctl.send_setpoint(sp)
        assert ctl.recv_feedback(fb, 0.0) is False  # nothing before the tick
        assert select.select((ep,), (), (), 5.0)[0]
        step(0)
        assert ctl.recv_feedback(fb, 5.0)
        assert fb.seq == 7
        assert fb.time_s == pytest.approx(step.plant.pwm_period, rel=1e-12)
        for k in range(1, 400):
            step(k)
        assert step.plant.output("encoder_counts") > 0.0
        assert step.link() == {"setpoints": 1, "feedbacks": 400, "ticks_without_setpoint": 399}


def test_adapter_needs_the_plant():
    with pytest.raises(ValueError, match="needs with_plant"):
        bench_loop.run([1000], 0.1, with_plant=False, adapter="udp")
