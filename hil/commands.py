"""``hil sim`` and ``hil measure``: lock-step runs that write files a person opens.

Units at this edge are the CNC's: mm, mm/min and A (deg and deg/min on rotary
tables); everything inside is SI.
"""

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hil.controller.config import axis_limits, clamp_codes, cnc_unit, load_controller
from hil.controller.interpolator import SETTLE_S, plan
from hil.controller.program import read_program
from hil.figures import plot_sim, plot_step
from hil.measure.frequency_response import bandwidth_hz, bode_plot, peaks, write_csv
from hil.measure.runs import bode, current_step, position_step, speed_step, write_step_csv
from hil.measure.trace import TraceConfigError, TraceRecorder, Trigger
from hil.progress import COMPILING, Progress
from hil.sim import TRACE_METADATA, LockStep, mean_columns_note, servo_trace_columns
from hil.trace_file import write_trace
from plant.assemble import transmission_ratio
from plant.config import MachineConfig, load_machine

#: resonance peaks are reported down to this far below the low-frequency gain, dB
PEAK_RANGE_DB = 20.0


#: a fraction of the work is shown as this many parts (hil.progress counts whole steps)
_PARTS = 1000




def _progress(p: Progress) -> Callable[[float], None]:
    """A fraction-done callback (what LockStep.run and the PRBS runs call) feeding ``p``."""
    return lambda fraction: p.update(round(_PARTS * fraction))


def _axis_letter(cfg: MachineConfig, axis: str | None) -> str:
    return axis or ("C" if cfg.machine.kind == "rotary" else "X")


def parse_trigger(spec: str) -> Trigger:
    """``COLUMN:edge``, ``COLUMN:LEVEL`` or ``COLUMN:LEVEL:rising|falling|either`` (a servo
    trace column and a level in its unit), or ``immediate``."""
    parts = spec.split(":")
    try:
        if parts == ["immediate"]:
            return Trigger()
        if len(parts) == 2 and parts[1] == "edge":
            return Trigger.edge(parts[0])
        if len(parts) in (2, 3):
            return Trigger.level(parts[0], float(parts[1]), *parts[2:])
    except (ValueError, TraceConfigError) as exc:
        raise KeyError(f"trigger {spec!r}: {exc}") from exc
    raise KeyError(f"trigger {spec!r}: expected COLUMN:edge, COLUMN:LEVEL[:rising|falling|"
                   "either] or immediate")


def triggered_trace(columns: dict, trigger: Trigger, depth: int, pre: int):
    """Feed the servo-trace ``columns`` (t_s first) row by row through a triggered recorder,
    as the NC's servo trace records while the program runs; the Recording, or None when
    the trigger never fired or the run ended before ``depth`` samples."""
    names = [n for n in columns if n != "t_s"]
    dt = float(columns["t_s"][1] - columns["t_s"][0])
    try:
        rec = TraceRecorder(names, depth, pre, trigger, dt)
    except TraceConfigError as exc:
        raise KeyError(f"trace trigger: {exc} (columns: {', '.join(names)})") from exc
    rows = np.column_stack([columns[n] for n in names])
    for row in rows:
        rec.record(row)
        if rec.done:
            return rec.result()
    return None


def run_sim(config: Path, program: Path, out: Path, start: float, axis: str | None,
            every: int | None, trigger: str | None = None, depth: int = 1000,
            pre: int = 100, inject: tuple[str, ...] = ()) -> dict:
    """Simulate ``program`` on ``config`` from table position ``start`` (mm or deg);
    write trace.csv (one row per ``every`` ticks, default the position-control cycle) and
    sim.png into ``out``, and with a ``trigger`` (see :func:`parse_trigger`) triggered.csv:
    ``depth`` rows of which ``pre`` before the trigger; return a summary (CNC units) with
    the NC's alarms (``alarms``, empty when none was raised).  ``inject``: ``--inject``
    flags (:mod:`hil.inject`); every injection is named in the traces' headers
    (``injected_N``) and its events in the summary."""
    trig = parse_trigger(trigger) if trigger else None
    cfg = load_machine(config)
    k, unit = cnc_unit(cfg)
    x0 = start / k
    sec = load_controller(cfg)
    prog = read_program(program, axis=_axis_letter(cfg, axis), start=x0, clamp=clamp_codes(sec))
    profile = plan(prog, axis_limits(cfg, sec))
    with Progress(COMPILING, ticking=True):  # numba compiles here on a cold cache
        ls = LockStep(cfg, x0, axis=prog.axis, inject=inject)
        ls.enable()
    profile = ls.ctrl.run_profile(profile)  # ended before a block beyond the soft limits
    with Progress("simulating", total=_PARTS) as p:
        res = ls.run(profile.duration_s + SETTLE_S, _progress(p))
    out.mkdir(parents=True, exist_ok=True)
    meta = {"machine": str(config), "program": str(program), "axis": prog.axis,
            "source": "hil sim (lock-step)", **TRACE_METADATA,
            **{f"injected_{i + 1}": inj.describe()
               for i, inj in enumerate(ls.injectors[0].injections)}}
    every = every or ls.ctrl.sec.position_cycle_ratio
    columns = servo_trace_columns(res, every)
    notes = [mean_columns_note(res)]
    write_trace(out / "trace.csv", columns, meta, notes)
    plot_sim(res, out / "sim.png", f"{cfg.machine.name}: {program.name}")
    summary = {}
    if trig is not None:
        recording = triggered_trace(columns, trig, depth, pre)
        if recording is None:
            summary["triggered"] = f"trigger {trigger!r} did not complete a recording"
        else:
            write_trace(out / "triggered.csv", recording, {**meta, "trigger": trigger,
                                                             "pre_trigger_samples": pre},
                        notes)
            summary["triggered"] = str(out / "triggered.csv")
    fe = res["following_error"] * k
    return {**summary, "duration_s": float(res["t_s"][-1] - res["t_s"][0]),
            f"following_error_max_{unit}": float(abs(fe).max()),
            f"following_error_rms_{unit}": float((fe ** 2).mean() ** 0.5),
            f"contour_deviation_max_{unit}": float(abs(res["contour_deviation"]).max() * k),
            f"final_position_{unit}": float(res["x_act"][-1] * k),
            "alarms": ls.ctrl.alarms.as_dicts(),
            "injections": [f"{e.t_s:.4f} s {e.kind}: {e.reason}"
                           for e in ls.injectors[0].events],
            "trace": str(out / "trace.csv"), "plot": str(out / "sim.png")}


def run_step(config: Path, loop: str, amplitude: float, at: float, out: Path) -> dict:
    """A step of the current (A), speed (mm/min or deg/min) or position (mm or deg) loop
    starting at table position ``at``; writes step_<loop>.png and .csv.  The summary lists
    the NC's alarms (the step runs without the axis monitoring of programs, so only a
    bad feedback value, a drive fault or a non-finite loop state raises one)."""
    cfg = load_machine(config)
    k, unit = cnc_unit(cfg)
    x0 = at / k
    if loop == "current":
        res, scale, shown = current_step(cfg, amplitude, x0=x0), 1.0, "A"
    elif loop == "speed":
        res = speed_step(cfg, amplitude / k / 60.0, x0=x0)
        scale, shown = k * 60.0, f"{unit}/min"
    else:
        res, scale, shown = position_step(cfg, x0, amplitude / k), k, unit
    out.mkdir(parents=True, exist_ok=True)
    plot_step(res, out / f"step_{loop}.png", f"{cfg.machine.name}: {loop} step "
              f"{amplitude:g} {shown}", scale, shown)
    write_step_csv(out / f"step_{loop}.csv", res)
    return {"loop": loop, "step": amplitude, "unit": shown,
            "rise_time_ms": res.rise_time_s * 1e3, "overshoot_pct": res.overshoot_pct,
            "final": res.final * scale, "alarms": [a.message() for a in res.sim.alarms],
            "plot": str(out / f"step_{loop}.png")}


def run_bode(config: Path, loop: str, amplitude: float, offset: float, order: int,
             periods: int, at: float, out: Path) -> dict:
    """Frequency response of the current loop (A) or the speed loop (mm/min or deg/min at
    the table); writes bode_<loop>.png (magnitude with the -3 dB bandwidth and the peaks
    it reports marked, phase, coherence) and bode_<loop>.csv (freq_hz, magnitude_db,
    phase_deg, coherence)."""
    cfg = load_machine(config)
    k, _ = cnc_unit(cfg)
    if loop == "speed":
        ratio = transmission_ratio(cfg)
        amplitude, offset = amplitude / k / 60.0 / ratio, offset / k / 60.0 / ratio
    with Progress(f"{loop}-loop PRBS", total=_PARTS) as p:
        m = bode(cfg, loop, amplitude, offset, order=order, periods=periods, x0=at / k,
                 progress=_progress(p))
    fr = m.response
    # resonances a person cares about, not noise ripple near Nyquist far below the pass band
    floor_db = fr.magnitude_db[0] - PEAK_RANGE_DB
    shown = tuple(p for p in peaks(fr) if p.magnitude_db > floor_db)
    out.mkdir(parents=True, exist_ok=True)
    bode_plot(fr, out / f"bode_{loop}.png",
              f"{cfg.machine.name}: {loop}-loop frequency response", marked_peaks=shown)
    write_csv(out / f"bode_{loop}.csv", fr)
    return {"loop": loop, "bandwidth_hz": bandwidth_hz(fr),
            "peaks_hz": [round(p.freq_hz, 1) for p in shown],
            "alarms": [a.message() for a in m.sim.alarms], "plot": str(out / f"bode_{loop}.png")}


def print_summary(summary: dict, as_json: bool) -> None:
    """JSON, or one 'key: value' line per entry (the alarms one line each, as their
    messages, or 'alarms: none')."""
    if as_json:
        print(json.dumps(summary, indent=1))
        return
    for key, value in summary.items():
        if key == "alarms":
            lines = [f"alarm: {a['message'] if isinstance(a, dict) else a}" for a in value]
            print("\n".join(lines) or "alarms: none")
        else:
            print(f"{key}: {value:.6g}" if isinstance(value, float) else f"{key}: {value}")
