"""``hil bench loop --with-plant --adapter udp [--config MANIFEST]`` (issues 12 part 8
and 29): ``hil run``'s loop (the UDP adapter's device end, the drives, the recording
ring, the compiled loop) under the real-time request, a controller child on the other
end, and cyclictest's samples beyond the tick's slack.

Timing figures are not asserted (wall clock); what went over the link is: every tick
answers the controller once it is heard, the setpoints are the controller's, and the
compiled loop runs the steady ticks, many a call.
"""

import pytest

from hil.bench import loop as bench_loop
from hil.rt.cyclictest import samples_beyond
from tests.conftest import CONFIGS


@pytest.mark.parametrize("rate_hz", [8000, 2000])
def test_loop_with_the_emulator_over_udp_counts_the_link(monkeypatch, tmp_path, rate_hz):
    """0.3 s (cyclictest kept off PATH: its columns are null): feedback once the
    controller is heard, its setpoints taken, and the compiled loop running the steady
    ticks at 8 kHz (one drive cycle a tick) and at 2 kHz (four), many a call."""
    monkeypatch.setenv("PATH", str(tmp_path))
    (row,) = bench_loop.run([rate_hz], 0.3, with_plant=True, adapter="udp")
    assert row["adapter"] == "udp" and row["with_plant"] is True and row["axes"] == 1
    assert row["rate_hz"] == rate_hz and row["ticks"] == round(0.3 * rate_hz)
    link = row["link"]
    assert 0 < link["setpoints"] <= link["feedbacks"] <= row["ticks"]
    assert link["ticks_without_setpoint"] == row["ticks"] - link["setpoints"]
    assert 0 < link["compiled_ticks"] <= row["ticks"]  # silent ticks run compiled too
    assert link["compiled_ticks"] > 5 * link["compiled_calls"]
    # the sleep's end after its target, never before it (an absolute clock_nanosleep)
    assert 0.0 <= row["wake_latency_us"]["p50"] <= row["wake_latency_us"]["max"]
    assert row["cyclictest_us"] is None and row["cyclictest_beyond"] is None


def test_a_manifest_at_its_own_rate(monkeypatch, tmp_path):
    """--config MANIFEST without --rate: the machine's axes at its PWM frequency."""
    monkeypatch.setenv("PATH", str(tmp_path))
    (row,) = bench_loop.run([None], 0.2, with_plant=True, adapter="udp",
                            config=CONFIGS / "machines" / "arrow500_xy.toml")
    assert row["axes"] == 2 and row["rate_hz"] == 8000.0
    assert row["link"]["compiled_ticks"] > 0


def test_cyclictest_samples_beyond_a_threshold():
    """The count the overruns are judged against, from cyclictest's histogram: bins at
    or above the threshold, and the overflows past its range."""
    text = ("# Histogram\n000000 5\n000001 90\n000050 3\n000099 1\n"
            "# Max Latencies: 00250\n# Histogram Overflows: 00002\n")
    assert samples_beyond(text, 50.0) == (6, 101)
    assert samples_beyond(text, 49.5) == (6, 101)
    assert samples_beyond(text, 50.5) == (3, 101)


def test_adapter_needs_the_plant():
    with pytest.raises(ValueError, match="needs with_plant"):
        bench_loop.run([1000], 0.1, with_plant=False, adapter="udp")
