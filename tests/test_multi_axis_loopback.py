"""Loopback of a two-axis machine: ``hil controller`` and ``hil run`` as separate processes
over UDP, one message per tick carrying both axes (wire version 2), running
``programs/xy_moves.nc`` (both axes on straight lines), against the lock-step simulation
of the whole machine (:class:`hil.sim.MachineLockStep`).

Setup and tolerance as in ``tests/test_loopback.py``, whose docstring gives the reasons:
the Arrow 500 XY at 2 kHz (each axis the ``SLOW_2KHZ`` variant; Y a copy of X with a
550 kg slide), the rows clear of every timing fault's effect
(:func:`hil.runtime.sync.settled_rows`) compared, at least MIN_CLEAR of them, at most
ATTEMPTS runs; on them max |FE difference| <= 2 % of the lock-step maximum |FE| of that
axis, and each axis's final position within ten scale counts (1 µm: where an axis sticks
at the end of its last move depends on which of its ticks ran late).
"""

from pathlib import Path

import numpy as np
import pytest

from hil.commands import SETTLE_S
from hil.trace_file import read_trace
from plant.machines import load_machine_set
from tests.conftest import ROOT
from tests.runtime_helpers import machine_lockstep_traces, usable_loopback
from tests.test_multi_axis import ARROW, SLOW, write_manifest

PROGRAM = ROOT / "programs" / "xy_moves.nc"
TOLERANCE = 0.02
FINAL_COUNTS = 10
MIN_CLEAR = 0.2
ATTEMPTS = 3


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    return write_manifest(tmp_path_factory.mktemp("cfg") / "xy_2khz.toml", [
        ("X", ARROW, SLOW), ("Y", ARROW, {**SLOW, "table": {"mass_kg": 550.0}})])


@pytest.fixture(scope="module")
def lockstep(config, tmp_path_factory) -> dict[str, Path]:
    """Each axis's trace.csv of the machine's lock-step simulation of PROGRAM."""
    return machine_lockstep_traces(config, PROGRAM, SETTLE_S,
                                   tmp_path_factory.mktemp("lockstep"))


def test_two_axes_over_udp_match_the_machine_lockstep(config, lockstep, tmp_path):
    folder, summary, report, clear = usable_loopback(config, PROGRAM, tmp_path, ATTEMPTS,
                                                     MIN_CLEAR)
    assert summary["result"] == "completed" and set(summary["axes"]) == {"X", "Y"}
    assert report["exit_status"] == 0 and not report["watchdog"]["events"]
    assert report["adapter"]["stats"]["malformed"] == 0
    assert [a["name"] for a in report["axes"]] == ["X", "Y"]
    machine = load_machine_set(config)
    for name, cfg in zip(machine.names, machine.configs):
        ref = lockstep[name]
        t, t_ref = (read_trace(p) for p in (folder / "controller" / f"trace_{name}.csv", ref))
        fe = t.column("pos_set_mm") - t.column("pos_mm")
        fe_ref = t_ref.column("pos_set_mm") - t_ref.column("pos_mm")
        n = min(fe.size, fe_ref.size)
        keep = clear[name][:n]
        diff = np.abs(fe[:n] - fe_ref[:n])
        worst, allowed = diff[keep].max(), TOLERANCE * np.abs(fe_ref).max()
        print(f"\n{name}: {keep.sum()} of {n} rows clear; max |FE diff| {worst * 1e3:.2f} µm "
              f"(allowed {allowed * 1e3:.2f}); lock-step max |FE| "
              f"{np.abs(fe_ref).max() * 1e3:.1f} µm")
        assert worst <= allowed, f"{name}: row {np.flatnonzero(keep & (diff > allowed))[0]}"
        final, final_ref = t.column("pos_mm")[-1], t_ref.column("pos_mm")[-1]
        scale_mm = cfg.sensors.scale_resolution_m * 1e3
        assert abs(final - final_ref) <= FINAL_COUNTS * scale_mm + 1e-12
