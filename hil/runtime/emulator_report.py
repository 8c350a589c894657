"""What ``hil run`` writes about its run: the recording's metadata, the events that close
it (why it stopped, the safe state), and ``report.json``.

Functions of a :class:`~hil.runtime.emulator.Emulator`'s state, called by its life cycle;
they read it and change nothing.
"""

import time
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

from hil.report.host import host_fingerprint
from hil.rt.loop import LoopStats
from hil.rt.scheduling import last_cpu
from hil.runtime.common import scheduling_dict
from hil.runtime.run_events import RunEvent
from hil.runtime.timing_quality import TimingQuality
from plant import layout as L


def runtime_dict(emu) -> dict:
    """The runtime settings, JSON-ready."""
    return {k: str(v) if isinstance(v, Path) else v for k, v in asdict(emu.rc).items()}


def metadata(emu) -> dict:
    """The recording's metadata (JSON-ready): the machine file(s) with their text (the
    manifest first), the runtime settings and timing, the adapter URL, and per axis what
    an export needs: ``table_per_count`` (table units, m or rad, per motor-encoder count:
    a CSP target's unit), ``scale_resolution_m`` and the axis's column prefix; and the
    fault injections known at the start (machine file, ``--inject``; those arriving over
    the adapter are events of the recording and listed in ``report.json``); and the
    wall clock beside the drive's (``clock``: ``unix_ns`` read between two readings of
    the monotonic clock, ``monotonic_ns`` their middle), so that what other tools stamped
    in wall-clock time (a CAN bus log) can be placed on the run's time; and
    ``inject_port``: the bench's injection port, ``HOST:PORT`` (``--inject-port``; None:
    none), where ``hil scope``'s page sends the injections of its panel."""
    m, t = emu.machine, emu.timing
    files = ([Path(m.path)] if m.manifest else []) + [Path(c.path) for c in m.configs]
    axes = [{"name": a.name, "machine_file": a.config.path, "kind": a.config.machine.kind,
             "table_per_count": p.built.ratio / p.params[L.P_ENC_COUNTS_PER_RAD],
             "scale_resolution_m": a.config.sensors.scale_resolution_m,
             "prefix": f"{a.name}_" if m.multi_axis else "",
             "injections": [i.as_dict() for i in inj.injections]}
            for a, p, inj in zip(m.axes, emu.plants, emu.injectors)]
    return {"command": "hil run", "machine": m.name, "machine_file": str(emu.rc.machine_file),
            "machine_files": {str(f): f.read_text() for f in dict.fromkeys(files)},
            "axes": axes, "runtime": runtime_dict(emu), "period_ns": t.period_ns,
            "rate_hz": t.rate_hz, "cycles_per_tick": t.cycles_per_tick,
            "pwm_frequency_hz": emu.cfg.motor.pwm_frequency_hz, "adapter": emu.url,
            "inject_port": None if emu.inject_port is None else emu.inject_port.url,
            "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "clock": _clock_pair()}


def _clock_pair() -> dict:
    """The wall clock and the monotonic clock at one moment, ns (see :func:`metadata`)."""
    m0 = time.monotonic_ns()
    unix = time.time_ns()
    m1 = time.monotonic_ns()
    return {"unix_ns": unix, "monotonic_ns": (m0 + m1) // 2}


def stop_reason(emu, stats: LoopStats) -> str:
    """Why the loop stopped, in words."""
    if emu.recording_failure is not None:
        return f"the recording failed: {emu.recording_failure}"
    if stats.stopped_by == "completed":
        return f"--duration {emu.rc.duration_s:g} s done"
    if stats.stopped_by == "overruns":
        return f"{stats.overruns} overruns (--overrun stop)"
    return "SIGTERM/SIGINT"


def final_events(emu, stats: LoopStats, safe: dict) -> list[RunEvent]:
    """Why the run stopped and the safe state each axis reached (tick -1: after the loop;
    the drive cycle it was reached in); ``safe`` as ``Emulator.safe_state`` returns it."""
    events = [RunEvent(-1, "", "emulator", "stopped",
                       f"after {stats.ticks} ticks: {stop_reason(emu, stats)}")]
    per_axis = safe if emu.machine.multi_axis else {emu.machine.names[0]: safe}
    for name, st in per_axis.items():
        events.append(RunEvent(-1, name, "emulator", "safe state",
                               f"{st['state']}, power stage "
                               f"{'on' if st['plant_enable'] else 'off'}, statusword "
                               f"{st['statusword']}", code=int(st["error_code"], 16),
                               cycle=st["cycle"]))
    return events


def run_report(emu, stats: LoopStats, granted, safe: dict, status: int) -> dict:
    """``report.json``: the keys ``hil report`` reads (loop, scheduling, adapter, host)
    and the daemon's own."""
    rc, t, m = emu.rc, emu.timing, emu.machine
    report = {
        "command": "hil run", "machine_file": str(rc.machine_file),
        "machine": m.name, "exit_status": status, "stopped": stop_reason(emu, stats),
        "axes": [{"name": a.name, "machine_file": a.config.path,
                  "machine": a.config.machine.name} for a in m.axes],
        "runtime": {**runtime_dict(emu), **asdict(t),
                    "cpu_used": rc.cpu if rc.cpu is not None else last_cpu(),
                    "cpu_shared_with": emu.cpu_shared_with,
                    "pwm_frequency_hz": emu.cfg.motor.pwm_frequency_hz},
        "loop": stats.as_dict(), "scheduling": scheduling_dict(granted),
        "adapter": {"name": emu.url, "stats": asdict(emu.endpoint.stats),
                    "rx_budget": getattr(emu.endpoint, "rx_budget", None)},
        "adapter_errors": asdict(emu.errors),
        "inject_port": None if emu.inject_port is None else {
            "address": emu.inject_port.url, "stats": asdict(emu.inject_port.stats)},
        "sync_lock": None if emu.sync_lock is None else emu.sync_lock.as_dict(),
        "compiled_loop": None if emu.steady is None else emu.steady.as_dict(),
        "helper_threads": emu.helper_threads,
        "setpoints": {"ticks_with_new_setpoint": emu.setpoints_heard,
                      "last_seq": int(emu.sp.seq)},
        "watchdog": emu.watchdog.as_dict(), "safe_state": safe,
        "faults": {name: d.faults.as_dict() for name, d in zip(m.names, emu.drives.drives)},
        "injections": {name: {"taken": [i.as_dict() for i in inj.injections],
                              "levels_at_end": inj.state()}
                       for name, inj in zip(m.names, emu.injectors)},
        "recording": {**emu.writer.as_dict(), "columns": {c.name: c.unit
                                                          for c in emu.recorder.specs}},
        "host": host_fingerprint(),
    }
    report["timing_quality"] = TimingQuality.of_emulator(report).as_dict()
    return report
