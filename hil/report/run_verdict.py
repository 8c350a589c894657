"""``hil report``'s verdict on a run: ``PASS`` or ``FAIL: <reasons>``, judged as ``hil
demo`` judges its own (:mod:`hil.runtime.demo_verdict`), on any run folder.

1. **The replay matches** the recording (:func:`hil.replay.replay_run`).  A run the
   replay cannot take (``can://``, whose link events it does not model) is said so, not
   failed.
2. **No alarm, fault or watchdog trip**: ``report.json``'s exit status, watchdog trips and
   drive faults; with ``--controller DIR`` that folder's ``summary.json`` too (its exit
   status and the NC's alarms).  A run without ``report.json`` (cut short) fails here.
3. **Timing.**  Where a lock-step reference exists -- ``--controller DIR`` of one axis,
   its program and start position known, no fault injected on either side -- the timing
   cost against it, within the tolerance this run's measured delays allow
   (:mod:`hil.replay.timing`): a larger difference is something other than timing.
   Without one, each side's counts against the limits of
   :mod:`hil.runtime.timing_quality` (overruns, late and missed messages at most 0.1 % of
   the ticks).  A stall (a loop that did not run for the watchdog's length) fails either
   way: no tolerance prices a loop that was not running.  :func:`judge_timing_counts`
   is the one rule, ``hil demo``'s too.

The lock-step trace is written into ``RUN/verdict_lockstep/``, the verdict into
``RUN/verdict.json``.
"""

import json
import math
from pathlib import Path

import numpy as np

from hil.commands import run_sim
from hil.replay import ReplayError, ReplayResult, replay_run
from hil.replay.timing import TimingCost, timing_cost
from hil.runtime.common import EXIT_OK, write_json
from hil.runtime.demo_verdict import (
    Verdict,
    check_processes,
    check_replay,
    check_timing,
)
from hil.runtime.record_reader import Recording
from hil.runtime.run_folder import REPORT
from hil.runtime.timing_quality import TimingQuality, same_moment
from plant.config import MachineConfig, load_machine
from plant.errors import ConfigError

VERDICT_JSON = "verdict.json"
LOCKSTEP_DIR = "verdict_lockstep"


def replay_or_reason(run: Path) -> ReplayResult | str:
    """The replay of ``run``, or why it could not be made."""
    try:
        return replay_run(run)
    except ReplayError as e:
        return str(e)


def timing_cost_of(run: Path, controller: Path, cfg: MachineConfig,
                   lockstep: Path) -> TimingCost | str:
    """The timing cost of ``run`` with ``controller``'s rows against the lock-step trace
    ``lockstep`` (:mod:`hil.replay.timing`), or why it could not be computed."""
    try:
        rec = Recording(run)
        with np.load(controller / "controller.npz") as npz:
            ctl = {k: npz[k] for k in npz.files}
        return timing_cost(rec.read(), ctl, lockstep, cfg, rec.period_ns * 1e-9)
    except (OSError, ValueError, KeyError) as e:  # RecordingError, TimingError, a trace
        return str(e)


def position_scale(cfg: MachineConfig) -> tuple[float, str]:
    """The factor and unit positions are shown in: µm, or mdeg on a rotary axis."""
    return (1e6, "µm") if cfg.machine.kind != "rotary" else (1e3 * 180 / math.pi, "mdeg")


def read_json(path: Path) -> dict | None:
    """A run's JSON file (``report.json``, ``summary.json``), or None when it is not there."""
    return json.loads(path.read_text()) if path.is_file() else None


def judge_lockstep_timing(v: Verdict, machine_file: Path, program: Path, start: float,
                          run: Path, controller: Path, out: Path
                          ) -> tuple[TimingCost | str, tuple[float, str]]:
    """Step 3's lock-step part: ``program`` simulated in lock-step on ``machine_file``
    from ``start`` (mm or deg) into ``out``, its alarms and the run's timing cost against
    it judged into ``v``; returns the cost (or why there is none) and the positions' scale
    (:func:`position_scale`).  Raises ConfigError, OSError or ValueError when the
    simulation cannot be run."""
    cfg = load_machine(machine_file)
    sim = run_sim(machine_file, program, out, start, None, None)
    for alarm in sim["alarms"]:
        v.fail(f"the lock-step simulation raised {alarm['message']}")
    cost = timing_cost_of(run, controller, cfg, Path(sim["trace"]))
    scale = position_scale(cfg)
    check_timing(v, cost, *scale)
    return cost, scale


def _lockstep_refused(report: dict, summary: dict) -> str | None:
    """Why the run has no lock-step reference, or None when it has one."""
    if "axes" in summary:
        return "a machine of several axes"
    if summary.get("injections_sent") or any(
            inj["taken"] for inj in report.get("injections", {}).values()):
        return "faults were injected"
    if not isinstance(summary.get("start"), (int, float)):
        return "the controller's summary has no start position (an older hil controller?)"
    if not Path(summary["program"]).is_file():
        return f"the program {summary['program']} is not there"
    return None


def _timing(v: Verdict, run: Path, controller: Path | None, report: dict,
            summary: dict | None) -> list[str]:
    """Step 3; returns the lines that show what it rests on."""
    lines = []
    refused = "no --controller folder" if summary is None else _lockstep_refused(report,
                                                                                summary)
    if refused is None:
        try:
            cost, (k, unit) = judge_lockstep_timing(
                v, Path(summary["machine_file"]), Path(summary["program"]),
                float(summary["start"]), run, controller, run / LOCKSTEP_DIR)
        except (ConfigError, OSError, ValueError) as e:
            refused = f"the lock-step simulation could not be run: {e}"
        else:
            lines.append("timing cost against the lock-step simulation: " + (
                f"not computed ({cost})" if isinstance(cost, str) else
                f"max {cost.diff_max * k:.2f} {unit} (tolerance "
                f"{cost.tolerance.value * k:.2f} {unit})"))
    if refused is not None:
        lines.append(f"no lock-step reference ({refused})")
    sides = judge_timing_counts(v, report, summary, priced=refused is None
                                and not isinstance(cost, str))
    return lines + [f"{side.side}: {side.line()}" for side in sides]


def judge_timing_counts(v: Verdict, report: dict, summary: dict | None,
                        priced: bool) -> list[TimingQuality]:
    """Step 3's counts of the emulator's ``report`` and the controller's ``summary`` (when
    given) into ``v``: stalls always, overruns and late or missed messages only when the
    lock-step reference did not price the timing (``priced``); each side's worst overrun
    as the verdict's context (shown if it fails); returns the sides."""
    sides = [TimingQuality.of_emulator(report)]
    if summary is not None:
        sides.append(TimingQuality.of_controller(summary))
    for side in sides:
        for reason in side.reasons(counts=not priced):
            v.fail(reason)
        if side.worst_overrun:
            v.context.append(side.worst_text())
    if len(sides) == 2 and (both := same_moment(*sides)):
        v.context.append(both)
    return sides


def judge_run(run: Path, controller: Path | None = None) -> tuple[Verdict, list[str]]:
    """The verdict on ``run`` (with ``controller``'s folder when given) and the lines
    that show what it rests on; also written into ``run/verdict.json``."""
    v = Verdict()
    report = read_json(run / REPORT)
    summary = None if controller is None else read_json(controller / "summary.json")
    lines = []
    if controller is not None and summary is None:
        v.fail(f"{controller} has no summary.json (hil controller did not end normally)")
    if report is None:
        v.fail("the emulator did not end normally (no report.json): the run was cut short")
    else:
        replay = replay_or_reason(run)
        if isinstance(replay, str):
            lines.append(f"recording = replay: not checked ({replay})")
        else:
            lines.append(f"recording = replay: {replay.line()}")
            check_replay(v, replay)
        check_processes(v, report["exit_status"],
                        EXIT_OK if summary is None else summary["exit_status"],
                        summary or {}, report)
        lines += _timing(v, run, controller, report, summary)
    write_json(run / VERDICT_JSON, {"verdict": v.line(), "reasons": v.reasons,
                                    "rests_on": lines})
    return v, lines
