"""Seed 001's five-axis machine in real time (issue 29's "done when"): ``hil run`` on
``configs/machines/geiss_5axis.toml`` at its 8 kHz against ``hil controller`` running
``programs/geiss_5axis_moves.nc`` (the linear axes on a line, all five on one line, a
rotary-only move, a rapid home), separate processes over UDP, one message a tick carrying
all five axes, both sides' ticks in their compiled loops (:mod:`hil.runtime.steady_tick`,
:mod:`hil.runtime.controller_steady`; the drives' power-off cycles before the enable
commands among them: five disabled axes in Python take 80-96 µs of the 125 µs).

Checked against the lock-step simulation of the whole machine
(:class:`hil.sim.MachineLockStep`, the same controller and plants in one process, no
wire): on the rows clear of every timing fault's effect
(:func:`hil.runtime.sync.settled_rows`, a glitch's effect taken to last
GLITCH_WINDOW_S), at least MIN_CLEAR of them, each axis's following error within the
larger of 2 % of its lock-step maximum and FLOOR_COUNTS position counts (where a tick's
setpoint lands within its period differs between the two), and each axis's final
position within FINAL_COUNTS scale counts (FINAL_DEG on a rotary axis); at most ATTEMPTS
runs (a shared CI machine may stall a run past use).  The emulator's report and the
controller's summary must show both compiled loops carrying the motion: most ticks
compiled, in calls of many ticks.
"""

import math

import numpy as np
import pytest

from hil.commands import SETTLE_S
from hil.controller.config import cnc_unit
from hil.runtime.steady_tick import BURST_S
from hil.trace_file import read_trace
from plant.machines import load_machine_set
from tests.conftest import CONFIGS, ROOT
from tests.runtime_helpers import machine_lockstep_traces, usable_loopback

CONFIG = CONFIGS / "machines" / "geiss_5axis.toml"
PROGRAM = ROOT / "programs" / "geiss_5axis_moves.nc"
TOLERANCE = 0.02
#: the smallest following-error difference judged, in position counts (the scale's, or a
#: direct-drive rotary axis's encoder's)
FLOOR_COUNTS = 20
FINAL_COUNTS = 10
#: ... on a rotary axis, whose encoder (2**26 counts a turn) resolves far below where
#: friction lets it stick: 0.2 mdeg, an arc of 1.7 µm at 500 mm
FINAL_DEG = 2e-4
#: how long a late tick's or a missing feedback's effect lasts: at 8 kHz a glitch of one or
#: two ticks in a rapid move still shows 30 ticks later (a few µm on X), the speed loop's
#: settling
GLITCH_WINDOW_S = 0.005
#: calls the enable sequence and the program's start may take besides those explained
START_CALLS = 20
#: rows clear of timing faults needed (at 8 kHz on a 2-vCPU machine two or three stalls
#: of a few hundred µs a run are usual, each clouding 0.2 s of a 1.4 s program)
MIN_CLEAR = 0.15
#: runs tried: on the 2-vCPU VM (2026-11-29), for a while, a run's emulator overran 100-130
#: times, its worst several ms late in a Python tick after the enable with no counter of
#: hil.rt.causes moving, and the controller then missed 30-90 feedbacks: four runs in a
#: row were unusable, then on the same tree and cache most were usable again (open)
ATTEMPTS = 8


@pytest.fixture(scope="module")
def lockstep(tmp_path_factory):
    return machine_lockstep_traces(CONFIG, PROGRAM, SETTLE_S,
                                   tmp_path_factory.mktemp("lockstep5"))


def test_five_axes_at_8khz_match_the_machine_lockstep(lockstep, tmp_path):
    folder, summary, report, clear = usable_loopback(CONFIG, PROGRAM, tmp_path, ATTEMPTS,
                                                     MIN_CLEAR, GLITCH_WINDOW_S)
    machine = load_machine_set(CONFIG)
    assert summary["result"] == "completed" and set(summary["axes"]) == set(machine.names)
    assert report["exit_status"] == 0 and not report["watchdog"]["events"]
    assert report["runtime"]["rate_hz"] == 8000.0
    assert report["adapter"]["stats"]["malformed"] == 0
    compiled = report["compiled_loop"]
    print(f"\nemulator's compiled loop: {compiled}; loop: {report['loop']['compute_us']}; "
          f"controller's: {summary['compiled_loop']}; loop: {summary['loop']['compute_us']}")
    # the program's motion and the holds around it run compiled on both sides, a call
    # ending only for what hil.runtime.steady_tick lists: an overrun (many on a loaded
    # machine), a declined tick, BURST_S of ticks, and the start's Python ticks
    for loop, stats in ((compiled, report["loop"]), (summary["compiled_loop"], summary["loop"])):
        assert loop["ticks"] >= 0.5 * summary["ticks_recorded"]
        explained = (stats["overruns"] + stats["grace_overruns"] + sum(loop["declined"].values())
                     + loop["ticks"] / (BURST_S * report["runtime"]["rate_hz"])
                     + START_CALLS)
        assert loop["calls"] <= explained, (loop, stats["overruns"])
    for name, cfg in zip(machine.names, machine.configs):
        t, t_ref = (read_trace(p) for p in (folder / "controller" / f"trace_{name}.csv",
                                             lockstep[name]))
        k, unit = cnc_unit(cfg)
        fe = t.column(f"pos_set_{unit}") - t.column(f"pos_{unit}")
        fe_ref = t_ref.column(f"pos_set_{unit}") - t_ref.column(f"pos_{unit}")
        n = min(fe.size, fe_ref.size)
        keep = clear[name][:n]
        diff = np.abs(fe[:n] - fe_ref[:n])
        count = position_count(cfg) * k
        worst = diff[keep].max()
        allowed = max(TOLERANCE * np.abs(fe_ref).max(), FLOOR_COUNTS * count)
        print(f"{name}: {keep.sum()} of {n} rows clear; max |FE diff| {worst:.6f} {unit} "
              f"(allowed {allowed:.6f}); lock-step max |FE| {np.abs(fe_ref).max():.6f}")
        assert worst <= allowed, f"{name}: row {np.flatnonzero(keep & (diff > allowed))[0]}"
        # where friction holds an axis at rest depends on the last moves' timing: the end
        # is compared only where the rows before it are clear of timing faults
        if not clear[name][fe.size - 1]:
            print(f"{name}: final position not compared (a timing fault within the settling "
                  f"window before the end)")
            continue
        final, final_ref = t.column(f"pos_{unit}")[-1], t_ref.column(f"pos_{unit}")[-1]
        assert abs(final - final_ref) <= (FINAL_COUNTS * count if unit == "mm" else FINAL_DEG) \
            + 1e-12, name


def position_count(cfg) -> float:
    """The axis's position resolution in SI (m or rad): its linear scale's count, or,
    without one (a direct-drive rotary axis), its motor encoder's."""
    if cfg.sensors.scale_resolution_m > 0.0:
        return cfg.sensors.scale_resolution_m
    return 2.0 * math.pi / cfg.sensors.encoder_counts_per_rev
