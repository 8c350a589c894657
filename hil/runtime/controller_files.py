"""What ``hil controller`` writes when its run ends: ``controller.npz``, the servo trace and
``summary.json`` (see :mod:`hil.runtime.controller_proc` for the columns).

One axis: ``trace.csv`` and the column names of :data:`FLOAT_COLUMNS`; the summary's
``following_error_max_<unit>``, ``following_error_rms_<unit>``, ``final_position_<unit>``
and ``program_end_<unit>`` are the axis's.  Several axes: ``trace_<AXIS>.csv`` per axis;
in ``controller.npz`` the columns ``t_s``, ``tick`` and ``fb_time_s`` (common to all axes:
one tick steps them all) and the integer columns once, every other float column per axis
with the letter in front (``X_following_error``); the summary's per-axis values under
``axes`` (each with its own unit and ``trace_every_ticks``), the top-level ones those of
the first axis.  ``alarms`` lists the NC's alarms of every axis (number, axis, text,
detail, tick, time ``t_s``, count, message) in the order raised; any alarm makes the run
fail.
"""

from dataclasses import asdict

import numpy as np

from hil.report.host import host_fingerprint
from hil.rt.loop import Percentiles
from hil.runtime.common import EXIT_FAILED, EXIT_OK, scheduling_dict, write_json
from hil.runtime.sync import Alignment, in_step
from hil.runtime.timing_quality import TimingQuality
from hil.sim import TRACE_METADATA, SimResult, servo_trace_columns
from hil.trace_file import write_trace

#: float columns of controller.npz: the controller's signals (hil.sim.SIGNALS names), then
#: the feedback's (motor_pos: the encoder angle, rad; fb_time_s: the drive's time stamp of
#: the cycle read)
FLOAT_COLUMNS = ("t_s", "x_set", "v_set", "a_set", "x_act", "v_act", "v_cmd", "w_set",
                 "w_act", "iq_set", "following_error", "contour_deviation", "iq_meas",
                 "motor_pos", "tick", "fb_time_s")
#: the controller's attributes recorded in FLOAT_COLUMNS' first columns (``t`` is t_s)
CTRL_SIGNALS = ("t", *FLOAT_COLUMNS[1:FLOAT_COLUMNS.index("iq_meas")])
#: float columns common to every axis
COMMON_FLOATS = ("t_s", "tick", "fb_time_s")
#: integer columns (see hil.runtime.controller_proc)
INT_COLUMNS = ("k", "fb_new", "lag_ticks", "round_trip_ns", "fb_sp_t_ns", "fb_t_ns",
               "fb_rx_ns")


def _axis_columns(proc, a: int, n: int) -> dict:
    return {name: proc.floats[:n, a, i].copy() for i, name in enumerate(FLOAT_COLUMNS)}


def _axis_summary(proc, a: int, cols: dict, trace) -> dict:
    k_cnc, u = proc.units[a]
    n = len(cols["t_s"])
    fe = cols["following_error"] * k_cnc
    return {f"following_error_max_{u}": float(np.abs(fe).max()) if n else None,
            f"following_error_rms_{u}": float(np.sqrt(np.mean(fe ** 2))) if n else None,
            f"contour_deviation_max_{u}": (float(np.abs(cols["contour_deviation"]).max()
                                            * k_cnc) if n else None),
            f"final_position_{u}": float(cols["x_act"][-1] * k_cnc) if n else None,
            f"program_end_{u}": proc.program_end[a] * k_cnc,
            "trace_every_ticks": proc.mctrl.ctrls[a].sec.position_cycle_ratio,
            "trace": None if trace is None else str(trace)}


def _trace(proc, a: int, cols: dict, name: str, timing: dict[str, str]):
    """Write the axis's servo trace (``timing``: the run's timing for its header); its
    path, or None when no row is due."""
    rc, ctrl = proc.rc, proc.mctrl.ctrls[a]
    every = ctrl.sec.position_cycle_ratio
    if not np.any(cols["tick"] % every == 0):
        return None
    # the servo trace's motor position is the encoder the controller read in the tick
    # (hil.sim's motor_pos_meas): this process's motor_pos column
    res = SimResult({**cols, "motor_pos_meas": cols["motor_pos"]}, ctrl.cfg.machine.kind,
                    ctrl.ratio, proc.period_s, scale_resolution_m=ctrl.scale_res)
    return write_trace(rc.out_dir / name, servo_trace_columns(res, every), {
        "machine": str(rc.machine_file), "program": str(rc.program_file),
        "axis": proc.machine.names[a], "source": f"hil controller over {rc.adapter_url}",
        **TRACE_METADATA, **timing})


def nc_summary(mctrl, nc_ns: np.ndarray) -> dict:
    """The NC's part of the recorded ticks (every axis's tick, ns per tick) and how many
    ticks each axis ran on its compiled path (:mod:`hil.controller.compiled_path`), with
    the statuses that handed a tick back to Python."""
    return {"tick_us": Percentiles.of_ns_in_us(nc_ns).as_dict(),
            "compiled_ticks": {c.axis: c.compiled.cycles if c.compiled else 0
                               for c in mctrl.ctrls},
            "declined": {c.axis: {str(k): v for k, v in c.compiled.exits.items()}
                         if c.compiled else {} for c in mctrl.ctrls}}


def write_outputs(proc, stats, granted, alignment: Alignment) -> dict:
    """Write the run folder of a finished :class:`~hil.runtime.controller_proc.
    ControllerProcess`; returns the summary (also in ``summary.json``)."""
    rc, n, names = proc.rc, proc.rows, proc.machine.names
    rc.out_dir.mkdir(parents=True, exist_ok=True)
    ints = {name: proc.ints[:n, i].copy() for i, name in enumerate(INT_COLUMNS)}
    per_axis = [_axis_columns(proc, a, n) for a in range(len(names))]
    multi = proc.machine.multi_axis
    if multi:
        saved = {c: per_axis[0][c] for c in COMMON_FLOATS}
        for name, cols in zip(names, per_axis):
            saved.update({f"{name}_{c}": v for c, v in cols.items() if c not in COMMON_FLOATS})
    else:
        saved = dict(per_axis[0])
    np.savez(rc.out_dir / "controller.npz", **saved, **ints, lateness_ns=stats.lateness_ns,
             compute_ns=stats.compute_ns, seq_minus_k=np.uint32(proc.seq_minus_k))
    cols = {**per_axis[0], **ints}
    new = cols["fb_new"] == 1
    lag = cols["lag_ticks"]
    delay = proc.delay_ticks
    drive_clock = getattr(proc.ep, "drive_clock", True)
    feedback = {"ticks_without_new": int(n - new.sum()),
                "ticks_in_step": int(in_step(cols, proc.period_s, delay, drive_clock).sum()),
                "delay_ticks": delay, "drive_clock": drive_clock,
                "lag_ticks": {"0": int((lag == 0).sum()), "1": int((lag == 1).sum()),
                              "2+": int((lag >= 2).sum())}}
    loop = stats.as_dict()
    quality = TimingQuality.of_controller({"loop": loop, "feedback": feedback})
    axes = {}
    for a, (name, cols_a) in enumerate(zip(names, per_axis)):
        trace = _trace(proc, a, cols_a, f"trace_{name}.csv" if multi else "trace.csv",
                       quality.header())
        axes[name] = _axis_summary(proc, a, cols_a, trace)
    first = axes[names[0]]
    alarms = proc.mctrl.alarm_dicts()
    summary = {
        "command": "hil controller", "result": proc.result,
        "exit_status": EXIT_OK if proc.result in ("completed", "stopped by SIGTERM/SIGINT")
        and not alarms else EXIT_FAILED,
        "alarms": alarms,
        "machine_file": str(rc.machine_file), "program": str(rc.program_file),
        "period_ns": proc.period_ns, "ticks_recorded": n, "ticks_planned": proc.n_run,
        **{k: v for k, v in first.items() if k != "trace"},
        "round_trip_us": Percentiles.of_ns_in_us(cols["round_trip_ns"][new]).as_dict(),
        "feedback": feedback, "alignment": alignment.as_dict(),
        "loop": loop, "scheduling": scheduling_dict(granted),
        "cpu_shared_with": proc.cpu_shared_with,
        "nc": nc_summary(proc.mctrl, proc.nc_ns[:n]),
        "compiled_loop": None if proc.steady is None else proc.steady.as_dict(),
        "adapter": {"name": rc.adapter_url, "stats": asdict(proc.ep.stats),
                    "errors": proc.adapter_errors},
        "injections_sent": [{"at_s": p.at_s, **p.request._asdict()}
                            for p in proc.injections.sent],
        "trace": first["trace"], "host": host_fingerprint(),
        "start": rc.start_cnc,
    }
    summary["timing_quality"] = quality.as_dict()
    if multi:
        summary["axes"] = axes
    write_json(rc.out_dir / "summary.json", summary)
    return summary
