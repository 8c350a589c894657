"""``hil linuxcnc INI --program FILE.ngc --out DIR``: LinuxCNC drives the emulated machine.

Starts ``hil run`` on the machine the INI names and LinuxCNC on the INI, headless
(:mod:`hil.linuxcnc.session`); turns the machine on, homes every joint on the emulated
home switch and index mark, runs the program, and prints LinuxCNC's own following error
beside the drive's and the verdict, the last line: ``PASS`` or ``FAIL: <reasons>``
(:mod:`hil.linuxcnc.verdict`).  ``--inject`` passes a fault to ``hil run``: LinuxCNC's
following-error protection is what should notice it.

Files in ``--out``: ``emulator/`` (hil run's recording.arrows, events.arrows,
report.json), ``linuxcnc/`` (the run's INI and HAL files, ``result.json`` of the display,
``ferror.txt``: every servo period's following error and limit per joint, the machine's
enable and the servo thread's period as it ran), ``emulator.log``, ``linuxcnc.log`` and
``linuxcnc.json`` (the following errors, the homing, the servo thread's timing while the
machine was on, the verdict).  Exit status 0 on PASS, 1 on FAIL, 2 when the
INI, the machine file or the program is refused, or LinuxCNC cannot be run here.
"""

import argparse
import json
import math
import sys
from pathlib import Path

from hil.controller.config import cnc_unit
from hil.inject import INJECT_HELP
from hil.inject.schedule import from_flags
from hil.linuxcnc import install, session
from hil.linuxcnc.install import LinuxCNCUnavailable
from hil.linuxcnc.session import FollowingError, LinuxCNCConfigError, SessionFiles
from hil.linuxcnc.verdict import Homing, ferror_lines, judge
from hil.replay import ReplayError, replay_run
from hil.runtime.common import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_OK, eprint, write_json
from plant import Plant
from plant import layout as L
from plant.config import MachineConfig
from plant.errors import ConfigError
from plant.machines import load_machine_set

#: the longest each phase of the session may take by default (machine on, homing, the
#: program), s
DEFAULT_TIMEOUT_S = 60.0
#: where built components are kept between runs
COMPONENT_CACHE = install.DEFAULT_PREFIX.parent / "components"


def index_above_switch(cfg: MachineConfig) -> float:
    """The emulated encoder's first index mark above the home switch's edge, increments:
    where LinuxCNC's homing (search the switch, latch its edge going up, on to the next
    index) must reset the feedback."""
    plant = Plant(cfg)
    p = plant.params
    edge = p[L.P_HOME_SWITCH] / plant.built.ratio * p[L.P_ENC_COUNTS_PER_RAD]
    per_mark = plant.counts_per_mark
    return float((math.floor(edge / per_mark) + 1) * per_mark)


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_linuxcnc(ini: Path, program: Path | None, out: Path, inject: list[str],
                 realtime: bool, timeout_s: float, cpu: int | None = None) -> int:
    """The whole command; returns the exit status."""
    try:  # refuse bad input before anything starts
        cfg = session.read_config(ini)
        machine = load_machine_set(cfg.machine)
        if len(machine.axes) != cfg.joints:
            raise LinuxCNCConfigError(f"{ini}: [KINS] JOINTS = {cfg.joints}, but {cfg.machine} "
                                      f"has {len(machine.axes)} axes")
        for i, axis_cfg in enumerate(machine.configs):  # hil run refuses them otherwise
            from_flags(inject, axis_cfg, i, machine.names)
        if program is not None and not program.is_file():
            raise LinuxCNCConfigError(f"--program {program}: no such file")
        lc = install.build_component(install.find(), COMPONENT_CACHE)
    except (LinuxCNCConfigError, ConfigError, LinuxCNCUnavailable) as e:
        eprint(f"hil linuxcnc: {e}")
        return EXIT_BAD_INPUT
    out.mkdir(parents=True, exist_ok=True)
    files = SessionFiles(out)
    for stale in (files.result, files.emulator / "report.json", out / "linuxcnc.json"):
        stale.unlink(missing_ok=True)  # an earlier run's files are not this run's
    processes = session.run(cfg, lc, files, program, session.EmulatorOptions(
        tuple(inject), realtime, cpu), timeout_s)
    result = _read_json(files.result)
    report = _read_json(files.emulator / "report.json")
    try:
        replay = replay_run(files.emulator)
    except ReplayError as e:
        replay = str(e)
    joints = (result or {}).get("joints", [])
    homing = [Homing(name, bool(j.get("homed")), j.get("index_counts"),
                     index_above_switch(c))
              for name, j, c in zip(machine.names, joints, machine.configs)]
    samples = session.read_samples(files.ferror, cfg.joints)
    lc_ferror = session.linuxcnc_ferror(samples, cfg.joints)
    timing = session.servo_timing(samples, cfg.joints, cfg.servo_period_ns)
    drive = session.drive_ferror(files.emulator, machine.names, cfg.scales)
    errors = [FollowingError(*lc_ferror[j], drive[j]) if lc_ferror else
              FollowingError(math.nan, math.nan, drive[j]) for j in range(cfg.joints)]
    verdict = judge(processes, result, homing, program is not None, report, replay)
    unit = cnc_unit(machine.configs[0])[1]
    print(f"hil linuxcnc: {machine.name}, {program.name if program else 'no program'}, "
          f"LinuxCNC over {processes.url}")
    for h in homing:
        print(f"joint {h.name}: homed at increment {h.index_counts} (the index above the "
              f"home switch: {h.expected_counts:.0f})")
    print("\n".join(ferror_lines(machine.names, errors, unit)))
    if timing is not None:
        print(timing.line())
    for error in (result or {}).get("errors", []):
        print(f"LinuxCNC at {error['t_s']:.3f} s: {error['text']}")
    print(f"files in {out}/")
    write_json(out / "linuxcnc.json", {
        "program": str(program) if program is not None else None,
        "url": processes.url, "emulator_exit": processes.emulator_status,
        "linuxcnc_exit": processes.linuxcnc_status, "phases": (result or {}).get("phases"),
        "linuxcnc_errors": (result or {}).get("errors"),
        "homing": [vars(h) for h in homing],
        "following_error": {name: {"linuxcnc_max": e.linuxcnc_max,
                                   "linuxcnc_limit": e.linuxcnc_limit,
                                   "drive_max": e.drive_max, "unit": unit}
                            for name, e in zip(machine.names, errors)},
        "servo_thread": timing.as_dict() if timing is not None else None,
        "rt_cpus": (result or {}).get("rt_cpus"),
        "replay": replay if isinstance(replay, str) else replay.as_dict(),
        "verdict": verdict.line(), "reasons": verdict.reasons})
    print(verdict.line())
    return EXIT_OK if verdict.passed else EXIT_FAILED


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil linuxcnc``."""
    p.add_argument("ini", help="LinuxCNC INI whose [FEEDDRIVE] section names the emulated "
                   "machine (configs/linuxcnc/arrow500_xyz.ini)")
    p.add_argument("--program", help="G-code program run after homing (none: home only)")
    p.add_argument("--out", default="linuxcnc-out", help="folder for every file (default "
                   "%(default)s)")
    p.add_argument("--inject", action="append", default=[],
                   metavar="[AXIS/]FAULT:KEY=VALUE,...", help=INJECT_HELP + "; passed to hil run")
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                   help="the longest each phase may take: machine on, homing, the program "
                   "(default %(default)g s)")
    p.add_argument("--no-rt", action="store_true", help="hil run without SCHED_FIFO")
    p.add_argument("--cpu", type=int, metavar="CPU", help="the CPU hil run's loop runs on "
                   "(default: hil run's, the last)")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil linuxcnc``: returns the exit status."""
    if not 0.0 < args.timeout < math.inf:
        eprint(f"hil linuxcnc: --timeout {args.timeout}: expected a positive time in s")
        return EXIT_BAD_INPUT
    return run_linuxcnc(Path(args.ini).resolve(),
                        Path(args.program).resolve() if args.program else None,
                        Path(args.out).resolve(), args.inject, not args.no_rt, args.timeout,
                        args.cpu)


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.linuxcnc.command``: the same as ``hil linuxcnc``."""
    parser = argparse.ArgumentParser(prog="hil linuxcnc", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
