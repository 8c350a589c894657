"""``hil identify RUN`` on a CST run: ``hil run --record`` with ``hil controller`` driving
the axis's current (the README's flow; issue 31 item 2).

The run is real: the emulator and the controller as processes over UDP, on the test axis
of ``tests/data/ident_screw.toml`` at 2 kHz (two Python loops keep up with it; where they
do not, the run's timing is beyond the limits, which the CST replay does not see: it feeds
the q-current setpoint the drive applied in each tick).  The emulator's machine file has
Coulomb friction 30 N.

* Identified with that file, the replay gives back the recorded positions to the last
  count and the current to its measurement noise.  Independent check: the machine file's
  own sensor steps and current noise (scale step / sqrt(12); hypot(current_noise_a,
  current_lsb_a / sqrt(12))), not the identification's floor.
* Identified with the file without Coulomb friction, Coulomb friction is named first.
  Independent check: the effect the test took out of the file.

On the code before issue 31 the loader refused the run (no CSP stretch).
"""

import math
import re

import numpy as np
import pytest

from hil.identify.fit import Identification
from hil.identify.record import Record, load_record, timing_warning
from plant.config import load_machine
from tests.conftest import ROOT
from tests.runtime_helpers import Children, python_module, terminate

BASE = ROOT / "tests" / "data" / "ident_screw.toml"
#: mm: the table's start, for the emulator and the controller
START_MM = 1.0
#: both directions, three feeds, two dwells: about 3 s
PROGRAM = ("N10 G90 G71\nN20 G1 X20 F3000\nN30 G4 F0.05\nN40 G1 X2 F3000\nN50 G4 F0.05\n"
           "N60 G1 X15 F1200\nN70 G1 X5 F600\nN80 G1 X12 F2000\nN90 M30\n")


#: mm, contour monitoring (MD36400, 1 mm by default): a loaded machine's late ticks made
#: the controller's deviation 1.1 mm and stopped the run with alarm 25050; what the test
#: needs is a run in CST, whatever its timing
CONTOUR_TOL_MM = 20.0


def _variant(path, **keys) -> object:
    """BASE at 2 kHz with the wider contour monitoring (``[controller]`` is its last
    section) and each ``key = value`` line of ``keys`` replaced, written to ``path``."""
    text = BASE.read_text() + f"contour_tol_mm = {CONTOUR_TOL_MM}\n"
    for key, value in {"pwm_frequency_hz": "2000.0", **keys}.items():
        text, n = re.subn(rf"^{key}\s*=.*$", f"{key} = {value}", text, flags=re.MULTILINE)
        assert n == 1, key
    path.write_text(text)
    return path


#: runs tried: on a loaded machine the controller may read feedback so late that the axis
#: overspeeds (8400h) or leaves the contour, and the program ends early
ATTEMPTS = 3


def _run(folder, truth, program):
    """``hil run --record`` and ``hil controller`` on ``truth`` over UDP: the run folder,
    or None (and the controller's log) when the controller did not complete the program."""
    run = folder / "run"
    with Children(folder) as children:
        emulator, served = children.emulator(truth, "udp://127.0.0.1:0", run, "--no-rt",
                                             "--start", START_MM)
        ctl = children.start("controller", python_module(
            "hil.runtime.controller_proc", truth, "--adapter", served, "--program", program,
            "--out", folder / "controller", "--start", START_MM, "--no-rt"))
        done = ctl.wait(timeout=120) == 0
        assert terminate(emulator) == 0, children.log("emulator")
        return (run if done else None), children.log("controller")


@pytest.fixture(scope="module")
def cst_run(tmp_path_factory):
    """(run folder, the emulator's machine file, the same without Coulomb friction)."""
    folder = tmp_path_factory.mktemp("cst_run")
    truth = _variant(folder / "truth.toml")
    no_coulomb = _variant(folder / "no_coulomb.toml", coulomb_n="0.0")
    program = folder / "moves.nc"
    program.write_text(PROGRAM)
    logs = []
    for attempt in range(ATTEMPTS):
        (folder / str(attempt)).mkdir()
        run, log = _run(folder / str(attempt), truth, program)
        if run is not None:
            return run, truth, no_coulomb
        logs.append(log)
    pytest.fail("no run completed its program:\n" + "\n".join(logs))


def test_the_loader_takes_the_cst_stretch_and_its_applied_current(cst_run):
    run, _, _ = cst_run
    rec = load_record(run)
    assert rec.applied == "current" and rec.meta["mode"] == "CST"
    assert rec.pos_set is None and rec.iq_set is not None
    assert rec.t[-1] > 2.5  # the program's moves, at the run's 0.5 ms ticks
    assert np.ptp(rec.pos) > 0.017  # it went from 1 mm to 20 mm and back
    assert timing_warning(rec) is None  # the applied current holds the run's timing


def test_the_emulators_own_file_replays_to_the_sensors_steps_and_adds_nothing(cst_run):
    run, truth, _ = cst_run
    cfg = load_machine(truth)
    sen = cfg.sensors
    ident = Identification(truth, load_record(run), refine_nfev=0).fit()
    after = ident.error_after
    assert ident.steps == []
    assert after["pos_rms_um"] <= sen.scale_resolution_m / math.sqrt(12) * 1e6
    count_um = cfg.mechanics.lead_m / sen.encoder_counts_per_rev * 1e6
    assert after["motor_pos_rms_um"] <= count_um / math.sqrt(12)
    noise = math.hypot(sen.current_noise_a, sen.current_lsb_a / math.sqrt(12))
    assert after["iq_rms_a"] <= 1.5 * noise


def test_coulomb_friction_left_out_of_the_file_is_named_first(cst_run):
    run, _, no_coulomb = cst_run
    ident = Identification(no_coulomb, load_record(run), refine_nfev=0).fit()
    added = [s.effect for s in ident.steps]
    assert added and added[0] == "coulomb_friction", added
    assert ident.error_after["pos_rms_um"] < ident.error_before["pos_rms_um"]


def _trace(meta: dict, applied: str = "position") -> Record:
    n = np.zeros(3)
    return Record(source="trace.csv", t=np.arange(3) * 1e-3, pos_set=n, pos=n, effort=n,
                  effort_kind="iq", iq_set=n, applied=applied,
                  meta={"timing_within_limits": "no", "timing_side": "emulator",
                        "timing_overruns": "9", **meta})


def test_the_timing_warning_advises_what_a_run_of_each_mode_replays():
    """A trace of a CST run is pointed at its run folder's applied current; a CSV run's at
    a run within the limits; a CSP run's own folder says what its replay misses; a trace
    of unknown mode (the controller's trace.csv) gets both modes' replays."""
    cst = timing_warning(_trace({"modes": "CST"}))
    assert "hil identify RUN" in cst and "q-current setpoint the drive applied" in cst
    assert "position targets" not in cst
    csv = timing_warning(_trace({"modes": "CSV"}))
    assert "none of CSV" in csv and "identify a run within the limits" in csv
    csp_run = timing_warning(_trace({"mode": "CSP"}))
    assert "at each position cycle" in csp_run and "hil identify RUN" not in csp_run
    unknown = timing_warning(_trace({}))
    assert "in CSP" in unknown and "in CST" in unknown
    assert timing_warning(_trace({"mode": "CST"}, applied="current")) is None
