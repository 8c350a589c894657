"""Which recorded ticks were exchanged as the lock-step simulation exchanges them
(:func:`hil.runtime.sync.in_step`) and which servo-trace rows are clear of a timing
fault's effect (:func:`hil.runtime.sync.settled_rows`), on hand-made controller columns
whose faults are known.  The first case is the pattern of a two-axis UDP loopback run in
which three ticks read the drive's feedback one cycle ahead: the tick in the middle
advanced by exactly one period from the tick before and had lag 0, was counted in step,
and its row's following error was one tick's travel (11 µm) off the lock-step run's."""

import numpy as np

from hil.runtime.sync import SETTLE_WINDOW_S, in_step, settled_rows

PERIOD_S = 0.5e-3
N = 3000


def columns(ahead: slice = slice(0), lag_at: tuple[int, ...] = (), skip_from: int | None = None,
            n: int = N) -> dict[str, np.ndarray]:
    """Controller columns of ``n`` ticks that each read the drive cycle of their own tick
    (a constant offset), except ``ahead`` (one cycle ahead), ``lag_at`` (lag 1) and, from
    ``skip_from`` on, one cycle ahead for good (the drive skipped a cycle)."""
    tick = np.arange(6, 6 + n, dtype=float)
    cycle = tick + 1357
    cycle[ahead] += 1
    if skip_from is not None:
        cycle[skip_from:] += 1
    lag = np.zeros(n, dtype=np.int64)
    lag[list(lag_at)] = 1
    return {"tick": tick, "fb_time_s": cycle * PERIOD_S, "lag_ticks": lag}


def test_ticks_reading_a_cycle_ahead_are_out_of_step_though_each_advanced_one_period():
    cols = columns(ahead=slice(1189, 1192), lag_at=(1191,))
    out = np.flatnonzero(~in_step(cols, PERIOD_S))
    assert out.tolist() == [1189, 1190, 1191, 1192]
    rows = settled_rows(cols, 4, PERIOD_S)
    # four ticks out of step are more than a glitch: the rows of the next SETTLE_WINDOW_S
    # are not clear, and the row of tick 1196 (index 1190, the middle one) is among them
    row_ticks = cols["tick"][cols["tick"] % 4 == 0]
    hidden = row_ticks[~rows]
    assert 1196 in hidden
    assert hidden.min() >= 1195 and hidden.max() <= 1198 + SETTLE_WINDOW_S / PERIOD_S


def test_a_lasting_change_of_offset_counts_out_only_where_it_happens():
    out = np.flatnonzero(~in_step(columns(skip_from=1500), PERIOD_S))
    assert out.tolist() == [1500]


def test_a_run_shorter_than_the_settle_window_is_in_step():
    assert in_step(columns(n=100), PERIOD_S).all()
    out = np.flatnonzero(~in_step(columns(ahead=slice(40, 42), n=100), PERIOD_S))
    assert out.tolist() == [40, 41, 42]


def test_without_the_drive_clock_the_lag_alone_decides():
    cols = columns(ahead=slice(1189, 1192), lag_at=(1191,))
    assert np.flatnonzero(~in_step(cols, PERIOD_S, drive_clock=False)).tolist() == [1191]


def test_no_ticks():
    empty = {"tick": np.zeros(0), "fb_time_s": np.zeros(0), "lag_ticks": np.zeros(0, int)}
    assert in_step(empty, PERIOD_S).size == 0
