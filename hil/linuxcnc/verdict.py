"""``hil linuxcnc``'s verdict: ``PASS`` or ``FAIL: <reasons>``, and what it rests on.

A session passes when all of these hold, and fails naming each that does not:

1. **LinuxCNC ran its course**: the display's result exists and no phase failed (machine
   on, homing, the program: each within the session's timeout), and LinuxCNC reported no
   error (its error and operator-error messages are the reasons, word for word: ``joint 0
   following error``, ``joint 1 amplifier fault``).
2. **Homing found the switch and the index**: every joint is homed, and the increment the
   feedback was reset to at the index (``feeddrive.N.index-counts``) is, within one count,
   the emulated encoder's first index mark above the home switch's edge: LinuxCNC's own
   homing sequence searched the switch, latched its edge and took the next mark.
3. **The program completed** (when one was given).
4. **The emulator is clean**: ``hil run`` exited 0, its report has no watchdog trip and no
   drive fault (:func:`hil.runtime.demo_verdict.check_processes`).
5. **The replay matches** the recording (:func:`hil.replay.replay_run`): the real-time run
   computed what the plant computes offline on the setpoints it applied.

The following errors (LinuxCNC's own and the drive's, :class:`~hil.linuxcnc.session.
FollowingError`) are reported beside the verdict; LinuxCNC judges its own against FERROR
and MIN_FERROR, and a trip is its message in step 1.
"""

from dataclasses import dataclass

from hil.linuxcnc.session import FollowingError, Processes
from hil.replay import ReplayResult
from hil.runtime.common import EXIT_OK
from hil.runtime.demo_verdict import Verdict, check_processes, check_replay

#: LinuxCNC's message kinds that are errors (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR)
ERROR_KINDS = frozenset((11, 13))


@dataclass(frozen=True)
class Homing:
    """One joint's homing.

    Attributes:
        name: the axis letter.
        homed: LinuxCNC says the joint is homed.
        index_counts: the increment the feedback was reset to at the index (None: the
            display did not read it).
        expected_counts: the emulated encoder's first index mark above the home switch's
            edge.
    """
    name: str
    homed: bool
    index_counts: float | None
    expected_counts: float


def check_linuxcnc(v: Verdict, processes: Processes, result: dict | None) -> None:
    """Step 1 (``result``: the display's JSON, None if it wrote none)."""
    if processes.problem:
        v.fail(processes.problem)
    if result is None:
        v.fail(f"LinuxCNC's display wrote no result (LinuxCNC exited with "
               f"{processes.linuxcnc_status}; see linuxcnc.log)")
        return
    for error in result["errors"]:
        if error["kind"] in ERROR_KINDS:
            v.fail(f"LinuxCNC: {error['text']}")
    if result["failed"] and not any(e["kind"] in ERROR_KINDS for e in result["errors"]):
        v.fail(result["failed"])


def check_homing(v: Verdict, homing: list[Homing]) -> None:
    """Step 2."""
    for h in homing:
        if not h.homed:
            v.fail(f"joint {h.name} was not homed")
        elif h.index_counts is None or abs(h.index_counts - h.expected_counts) > 1.0:
            v.fail(f"joint {h.name} homed at increment {h.index_counts}, not at the index "
                   f"mark above the home switch ({h.expected_counts:.0f})")


def check_program(v: Verdict, result: dict | None, program_given: bool) -> None:
    """Step 3."""
    if program_given and result is not None and not result["completed"] \
            and not v.reasons:
        v.fail("the program did not complete")


def judge(processes: Processes, result: dict | None, homing: list[Homing],
          program_given: bool, report: dict | None, replay: ReplayResult | str) -> Verdict:
    """Steps 1-5 (``report``: hil run's report.json, None if missing; ``replay``: the
    replay, or why there is none)."""
    v = Verdict()
    if processes.emulator_status is not None and processes.url is None:
        v.fail(processes.problem or "hil run did not start")  # nothing else ran
        return v
    check_linuxcnc(v, processes, result)
    if result is not None and "homed" in result["phases"]:  # else the failed phase says
        check_homing(v, homing)
    check_program(v, result, program_given)
    # the controller here is LinuxCNC, judged above: only the emulator's half is checked
    check_processes(v, processes.emulator_status if processes.emulator_status is not None
                    else -1, EXIT_OK, {}, report)
    check_replay(v, replay)
    return v


def ferror_lines(names: tuple[str, ...], errors: list[FollowingError], unit: str
                 ) -> list[str]:
    """The following errors beside each other, one line per joint."""
    return [f"joint {name}: following error, LinuxCNC's {e.linuxcnc_max:.4f} {unit} max "
            f"({100 * e.share:.0f} % of its limit there, {e.linuxcnc_limit:.4f} {unit}); "
            f"the drive's (target - encoder) {e.drive_max:.4f} {unit} max"
            for name, e in zip(names, errors)]
