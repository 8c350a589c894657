"""``hil demo``'s verdict: one line, ``PASS`` or ``FAIL: <reasons>``, and what it rests on.

A demo run passes when all of these hold, and fails naming each that does not:

1. **The replay matches** the recording (:func:`hil.replay.replay_run`: max relative
   difference <= 1e-9 on every drive word and plant output): the real-time run computed
   exactly what the plant computes offline on the setpoints it applied, so whatever else
   differs is timing.
2. **No alarm, fault or watchdog trip**: ``hil controller`` and ``hil run`` exited 0; the
   controller's ``summary.json`` lists no alarm; the emulator's ``report.json`` has no
   watchdog trip and no drive fault event; the lock-step simulation raised no alarm.
3. **The timing cost is within its tolerance**: max |FE_replay - FE_lockstep| on the
   program's servo-trace rows is within what this run's measured transport delay and
   jitter and the two loops' lateness can cause (:mod:`hil.replay.timing`, where the
   tolerance is derived): a larger difference is something other than timing.  And no
   loop stalled (:func:`hil.report.run_verdict.judge_timing_counts`, ``hil report``'s
   rule too: a loop that did not run for the watchdog's length fails whatever it cost).

A step that could not be made (a child that did not start, a replay refused) is a reason
of its own; the steps after it that need its files are not judged.
"""

from dataclasses import dataclass, field

from hil.replay import ReplayResult
from hil.replay.timing import TimingCost, Tolerance
from hil.runtime.common import EXIT_OK


@dataclass
class Verdict:
    """The reasons a demo run failed (none: it passed).

    Attributes:
        reasons: one phrase each, in the order checked.
        context: what a failed run's line adds after its reasons: each loop's worst
            overrun and what kept it (:meth:`hil.runtime.timing_quality.TimingQuality.
            worst_text`), so that a failure under load names its stall.
    """
    reasons: list[str] = field(default_factory=list)
    context: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.reasons

    def line(self) -> str:
        """``PASS`` or ``FAIL: reason; reason`` (and the context: ``| context; ...``)."""
        if self.passed:
            return "PASS"
        return "FAIL: " + "; ".join(self.reasons) + "".join(f" | {c}" for c in self.context)

    def fail(self, reason: str) -> None:
        self.reasons.append(reason)


def check_processes(v: Verdict, emu_status: int, ctl_status: int, controller: dict,
                    emulator: dict | None) -> None:
    """Step 2 for the two processes: exit statuses, the controller's alarms, the
    emulator's watchdog trips and drive faults (``controller``: summary.json, empty if
    missing; ``emulator``: report.json, None if missing)."""
    if ctl_status != EXIT_OK:
        v.fail(f"hil controller exited with {ctl_status}"
               + (f" ({controller['result']})" if controller.get("result") else ""))
    for alarm in controller.get("alarms", []):
        v.fail(f"the controller raised {alarm['message']}")
    if emulator is None:
        v.fail(f"hil run exited with {emu_status} and wrote no report.json")
        return
    if emu_status != EXIT_OK:
        v.fail(f"hil run exited with {emu_status} (stopped: {emulator['stopped']})")
    for event in emulator["watchdog"]["events"]:
        if event["kind"] == "tripped":
            v.fail(f"the emulator's watchdog tripped at t = {event['t_s']:.4f} s (tick "
                   f"{event['tick']}, {event['silent_ticks']} ticks without a setpoint)")
    for axis, faults in emulator["faults"].items():
        for event in faults["events"]:
            if event["kind"] == "fault":
                v.fail(f"axis {axis}: drive fault {event['code']:04X}h at drive cycle "
                       f"{event['cycle']} ({event['text']})")


def check_replay(v: Verdict, replay: ReplayResult | str) -> None:
    """Step 1 (``replay`` the result, or why the run could not be replayed)."""
    if isinstance(replay, str):
        v.fail(f"the run could not be replayed: {replay}")
    elif not replay.matches:
        w = replay.worst
        v.fail(f"the replay does not match the recording: {w.channel} at tick {w.tick} "
               f"differs by {w.rel_diff:.3g} relative (tolerance {replay.tolerance:g})")


def check_timing(v: Verdict, cost: TimingCost | str, k: float, unit: str) -> None:
    """Step 3 (``cost`` the timing cost, or why it could not be computed); ``k`` and
    ``unit`` show positions (1e6, "µm")."""
    if isinstance(cost, str):
        v.fail(f"the timing cost could not be computed: {cost}")
    elif not cost.within:
        t = cost.tolerance
        v.fail(f"timing cost {cost.diff_max * k:.2f} {unit} beyond its tolerance "
               f"{t.value * k:.2f} {unit} ({t.late_ticks} tick(s) late from "
               f"{timing_budget(t)})")


def timing_budget(t: Tolerance) -> str:
    """What the tolerance's ticks come from, in words with µs."""
    return (f"transport {t.delay_s * 1e6:.1f} µs + jitter {t.jitter_s * 1e6:.1f} µs + "
            f"controller lateness {t.controller_lateness_s * 1e6:.1f} µs + emulator "
            f"lateness {t.emulator_lateness_s * 1e6:.1f} µs")
