"""``hil bench loop --with-plant --adapter udp`` (issue 12 part 8): the emulator's real tick
(the UDP adapter's device end, the drive, the recording ring) in the real-time loop, a
controller child on the other end.

Timing figures are not asserted (wall clock); what went over the link is: every tick
answers the controller once it is heard, the setpoints are the controller's, the drive
is enabled and moved by them, and the compiled tick runs the steady ticks.
"""

import pytest

from hil.bench import loop as bench_loop
from hil.cia402 import State


@pytest.mark.parametrize("rate_hz", [8000, 2000])
def test_loop_with_the_emulator_over_udp_counts_the_link(monkeypatch, tmp_path, rate_hz):
    """0.3 s (cyclictest kept off PATH: its column is null): feedback once the controller
    is heard, its setpoints taken, the drive enabled, and the compiled tick running at
    8 kHz (one drive cycle a tick) and at 2 kHz (four)."""
    monkeypatch.setenv("PATH", str(tmp_path))
    states = []
    original = bench_loop.EmulatorTick.close

    def close(self):
        states.append(self.emulator.drive.sm.state)
        original(self)

    monkeypatch.setattr(bench_loop.EmulatorTick, "close", close)
    (row,) = bench_loop.run([rate_hz], 0.3, with_plant=True, adapter="udp")
    assert row["adapter"] == "udp" and row["with_plant"] is True
    link = row["link"]
    assert 0 < link["setpoints"] <= link["feedbacks"] <= row["ticks"]
    assert link["ticks_without_setpoint"] == row["ticks"] - link["setpoints"]
    assert states == [State.OPERATION_ENABLED]
    assert 0 < link["compiled_ticks"] <= row["ticks"]  # silent ticks run compiled too
    assert row["cyclictest_us"] is None


def test_adapter_needs_the_plant():
    with pytest.raises(ValueError, match="needs with_plant"):
        bench_loop.run([1000], 0.1, with_plant=False, adapter="udp")
