"""One headless LinuxCNC session against the emulator: ``hil run`` on the machine the INI
names, LinuxCNC on a copy of the INI for this run, and what both recorded.

1. The configuration (:func:`read_config`): the INI's ``[FEEDDRIVE]`` section names the
   emulated machine file (relative to the INI), where its tables start (``START``, as
   ``hil run --start``) and the emulator's ``ADDRESS``; ``[KINS] JOINTS`` and every
   ``[JOINT_N] SCALE`` (increments per joint unit) are read too.
2. ``hil run`` on that machine at ``udp://127.0.0.1:0?wire=fixed`` (a free port, read from its
   ``ready:`` line), recording into ``OUT/emulator``, with the ``--inject`` flags given.
3. LinuxCNC (:mod:`hil.linuxcnc.install`) on ``OUT/linuxcnc``: the INI's folder copied,
   ``ADDRESS`` set to the emulator's port, ``[DISPLAY] DISPLAY`` set to the headless display
   (:mod:`hil.linuxcnc.display`: machine on, home, the program, its result as JSON), and a
   HAL file of this run's own added: LinuxCNC's ``sampler`` taking every joint's following
   error and its limit (``joint.N.f-error``, ``joint.N.f-error-lim``), whether the
   machine is enabled, and the feeddrive component's view of the servo thread and the
   link (``feeddrive.period-ns``, ``stale-periods``, ``rx-frames``), every servo period,
   written by ``halsampler`` to ``OUT/linuxcnc/ferror.txt``.
4. When LinuxCNC has exited, SIGTERM to ``hil run`` (its clean stop writes report.json).

Every child has a timeout and is killed if it is still running when the session ends; each
wait longer than two seconds shows its progress on stderr (:mod:`hil.progress`).
"""

import configparser
import json
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from hil.linuxcnc import install
from hil.linuxcnc.install import LinuxCNC
from hil.progress import Progress
from hil.rt.loop import Percentiles
from hil.runtime.common import reap
from hil.runtime.demo import EMULATOR_STARTING, DemoError, wait_exit, wait_ready
from hil.runtime.record_reader import Recording, RecordingError

#: the headless display program LinuxCNC runs (in its own Python)
DISPLAY = Path(__file__).resolve().parent / "display.py"
#: longest wait for the emulator's ready line (a cold numba cache compiles for
#: :data:`~hil.progress.COLD_START_S`, more on a machine LinuxCNC's start keeps busy)
READY_TIMEOUT_S = 180.0
#: how long LinuxCNC's start and shut-down may take beyond the display's phases, s
LINUXCNC_MARGIN_S = 60.0
#: the display's phases (on, homing, the program, ...), each at most the session's timeout
PHASES = 4
#: longest wait for hil run's clean stop
STOP_TIMEOUT_S = 60.0
#: the sampler's FIFO, servo periods (halsampler empties it several times a second)
SAMPLER_DEPTH = 8192
#: the SCHED_FIFO priority of LinuxCNC's servo thread (below hil run's loop, 80 by default;
#: :func:`hil.linuxcnc.display.raise_realtime_threads` says why)
SERVO_PRIORITY = 70
#: the CiA 402 state OPERATION ENABLED in the recording's drive_state column
OPERATION_ENABLED = 4


class LinuxCNCConfigError(ValueError):
    """The INI cannot be used; the message names the file, the section and the key."""


@dataclass(frozen=True)
class LinuxCNCConfig:
    """What a session takes from a LinuxCNC INI (see the module docstring).

    Attributes:
        ini: the INI file.
        machine: the emulated machine file (a manifest of the joints' axes, or one axis).
        start: ``hil run --start`` (the tables' positions at start, mm or deg).
        scales: increments per joint unit, per joint ([JOINT_N] SCALE).
        servo_period_ns: LinuxCNC's servo thread period ([EMCMOT] SERVO_PERIOD), ns.
    """
    ini: Path
    machine: Path
    start: str
    scales: tuple[float, ...]
    servo_period_ns: int

    @property
    def joints(self) -> int:
        return len(self.scales)


def _ini(path: Path) -> configparser.ConfigParser:
    # LinuxCNC's INI repeats keys (HALFILE) and has no interpolation
    parser = configparser.ConfigParser(strict=False, interpolation=None,
                                       comment_prefixes=("#", ";"))
    parser.optionxform = str  # keys are case-sensitive
    try:
        with open(path) as f:
            parser.read_file(f)
    except (OSError, configparser.Error) as e:
        raise LinuxCNCConfigError(f"{path}: cannot read the INI: {e}") from e
    return parser


def read_config(ini: Path) -> LinuxCNCConfig:
    """The session's part of ``ini``; LinuxCNCConfigError naming the key otherwise."""
    parser = _ini(ini)

    def get(section: str, key: str) -> str:
        try:
            return parser[section][key].strip()
        except KeyError:
            raise LinuxCNCConfigError(f"{ini}: [{section}] {key} is missing") from None

    machine = (ini.parent / get("FEEDDRIVE", "MACHINE")).resolve()
    if not machine.exists():
        raise LinuxCNCConfigError(f"{ini}: [FEEDDRIVE] MACHINE = {machine}: no such file")
    try:
        joints = int(get("KINS", "JOINTS"))
        scales = tuple(float(get(f"JOINT_{j}", "SCALE")) for j in range(joints))
    except ValueError as e:
        raise LinuxCNCConfigError(f"{ini}: [KINS] JOINTS or a [JOINT_N] SCALE is not a "
                                  f"number: {e}") from e
    if not all(math.isfinite(s) and s != 0.0 for s in scales):
        raise LinuxCNCConfigError(f"{ini}: [JOINT_N] SCALE = {scales}: increments per unit, "
                                  f"finite and not 0")
    period = get("EMCMOT", "SERVO_PERIOD")
    if not period.isdigit() or int(period) == 0:
        raise LinuxCNCConfigError(f"{ini}: [EMCMOT] SERVO_PERIOD = {period}: expected a "
                                  f"whole number of ns above 0")
    return LinuxCNCConfig(ini.resolve(), machine, get("FEEDDRIVE", "START"), scales,
                          int(period))


def set_key(text: str, section: str, key: str, value: str) -> str:
    """``text`` (an INI) with ``key = value`` in ``section``: the key's first line there
    replaced, or the line added at the section's start."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.strip() == f"[{section}]"), None)
    if start is None:
        return text + f"\n[{section}]\n{key} = {value}\n"
    for i in range(start + 1, len(lines)):
        stripped = lines[i].strip()
        if stripped.startswith("["):
            break
        if stripped.split("=")[0].strip() == key and "=" in stripped:
            lines[i] = f"{key} = {value}"
            return "\n".join(lines) + "\n"
    lines.insert(start + 1, f"{key} = {value}")
    return "\n".join(lines) + "\n"


#: the sampler's pins after the joints' following errors and limits, with their HAL types
#: (bit, u32): the machine's enable, and the feeddrive component's period as it ran (ns),
#: periods without a new feedback and datagrams received (both counted from its start)
SAMPLED = (("motion.motion-enabled", "b"), ("feeddrive.period-ns", "u"),
           ("feeddrive.stale-periods", "u"), ("feeddrive.rx-frames", "u"))


def sampler_hal(joints: int) -> str:
    """The run's HAL file: every joint's following error and limit, and the pins of
    :data:`SAMPLED`, sampled every servo period."""
    cfg = "ff" * joints + "".join(kind for _, kind in SAMPLED)
    lines = [f"loadrt sampler depth={SAMPLER_DEPTH} cfg={cfg}", "addf sampler.0 servo-thread"]
    for j in range(joints):
        lines.append(f"net hil-ferror-{j} joint.{j}.f-error => sampler.0.pin.{j}")
        lines.append(f"net hil-ferror-lim-{j} joint.{j}.f-error-lim => "
                     f"sampler.0.pin.{joints + j}")
    for k, (pin, _) in enumerate(SAMPLED):
        lines.append(f"net hil-{pin.split('.')[-1]} {pin} => sampler.0.pin.{2 * joints + k}")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class SessionFiles:
    """Where a session's files are (under ``out``)."""
    out: Path

    @property
    def emulator(self) -> Path:
        return self.out / "emulator"

    @property
    def linuxcnc(self) -> Path:
        return self.out / "linuxcnc"

    @property
    def result(self) -> Path:
        return self.linuxcnc / "result.json"

    @property
    def ferror(self) -> Path:
        return self.linuxcnc / "ferror.txt"

    @property
    def run_ini(self) -> Path:
        return self.linuxcnc / "run.ini"


def prepare(cfg: LinuxCNCConfig, files: SessionFiles, program: Path | None,
            timeout_s: float, servo_priority: int | None) -> None:
    """``OUT/linuxcnc``: the INI's folder, the display (its settings: ``servo_priority``
    is the SCHED_FIFO priority of LinuxCNC's real-time threads, None: as LinuxCNC runs
    them) and the run's HAL file; the run's INI without the emulator's address yet."""
    shutil.rmtree(files.linuxcnc, ignore_errors=True)
    files.linuxcnc.mkdir(parents=True)
    for f in cfg.ini.parent.iterdir():
        if f.is_file():
            shutil.copy(f, files.linuxcnc / f.name)
    display = files.linuxcnc / DISPLAY.name
    shutil.copy(DISPLAY, display)
    display.chmod(display.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    (files.linuxcnc / "hil-sampler.hal").write_text(sampler_hal(cfg.joints))
    # the display's settings beside it: an INI line holds at most 255 characters
    (files.linuxcnc / "display.json").write_text(json.dumps({
        "result": str(files.result), "ferror": str(files.ferror), "timeout_s": timeout_s,
        "program": str(program) if program is not None else None,
        "servo_priority": servo_priority}))
    text = cfg.ini.read_text()
    text = set_key(text, "DISPLAY", "DISPLAY", str(display))
    text = set_key(text, "HAL", "HALFILE", _halfile(cfg.ini) + "\nHALFILE = hil-sampler.hal")
    files.run_ini.write_text(text)


def _halfile(ini: Path) -> str:
    """The INI's first HALFILE (the run's own follows it)."""
    try:
        return _ini(ini)["HAL"]["HALFILE"].strip()
    except KeyError:
        raise LinuxCNCConfigError(f"{ini}: [HAL] HALFILE is missing") from None


@dataclass(frozen=True)
class Processes:
    """How the session's two programs ended.

    Attributes:
        emulator_status: hil run's exit status (None: it did not start).
        linuxcnc_status: LinuxCNC's exit status (None: not started, or killed on its
            timeout).
        url: where the emulator served.
        problem: why the session stopped short (None: it ran to its end).
    """
    emulator_status: int | None
    linuxcnc_status: int | None
    url: str | None
    problem: str | None


@dataclass(frozen=True)
class EmulatorOptions:
    """How ``hil run`` runs in a session.

    Attributes:
        inject: its ``--inject`` flags.
        realtime: with SCHED_FIFO, pinning and locked memory (else ``--no-rt``).
        cpu: its ``--cpu`` (None: its default, the last CPU).
    """
    inject: tuple[str, ...] = ()
    realtime: bool = True
    cpu: int | None = None

    def argv(self) -> list[str]:
        return [*(f"--inject={flag}" for flag in self.inject),
                *([] if self.realtime else ["--no-rt"]),
                *([] if self.cpu is None else ["--cpu", str(self.cpu)])]


def run(cfg: LinuxCNCConfig, lc: LinuxCNC, files: SessionFiles, program: Path | None,
        emulator_options: EmulatorOptions, timeout_s: float) -> Processes:
    """The session (module docstring, steps 2-4); files under ``files.out``."""
    prepare(cfg, files, program, timeout_s,
            SERVO_PRIORITY if emulator_options.realtime else None)
    files.emulator.mkdir(parents=True, exist_ok=True)
    children: list[subprocess.Popen] = []
    children_dirs: list[Path] = []
    argv = [sys.executable, "-m", "hil.runtime.emulator", str(cfg.machine), "--adapter",
            "udp://127.0.0.1:0?wire=fixed", "--record", str(files.emulator), "--force",
            "--start", cfg.start, *emulator_options.argv()]
    try:
        with open(files.out / "emulator.log", "w") as log:
            emulator = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=log, text=True)
        children.append(emulator)
        try:
            with Progress(f"hil linuxcnc: {EMULATOR_STARTING}") as shown:
                url = wait_ready(emulator, READY_TIMEOUT_S, shown)
        except DemoError as e:
            return Processes(emulator.poll(), None, None, str(e))
        port = urlsplit(url).port
        files.run_ini.write_text(set_key(files.run_ini.read_text(), "FEEDDRIVE", "ADDRESS",
                                         f"127.0.0.1:{port}"))
        socket_dir = Path(tempfile.mkdtemp(prefix="hil-linuxcnc-"))
        children_dirs.append(socket_dir)
        env = install.environment(files.linuxcnc / "home", socket_dir)
        with open(files.out / "linuxcnc.log", "w") as log:
            linuxcnc = subprocess.Popen(lc.argv(["linuxcnc", str(files.run_ini)]),
                                        cwd=files.linuxcnc, env=env, stdout=log,
                                        stderr=subprocess.STDOUT, start_new_session=True)
        children.append(linuxcnc)
        limit = PHASES * timeout_s + LINUXCNC_MARGIN_S
        try:
            with Progress(f"hil linuxcnc: LinuxCNC starting, homing, running "
                          f"{program.name if program else 'no program'} and ending (up to "
                          f"{limit:g} s)") as shown:
                lc_status = wait_exit(linuxcnc, limit, shown)
            problem = None
        except subprocess.TimeoutExpired:
            os.killpg(linuxcnc.pid, signal.SIGKILL)
            linuxcnc.wait()
            lc_status, problem = None, f"LinuxCNC did not end within {limit:g} s"
        emulator.send_signal(signal.SIGTERM)
        try:
            with Progress("hil linuxcnc: hil run stopping (its recording and report written)",
                          ticking=True):
                emu_status = emulator.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            emu_status, problem = None, problem or "hil run did not stop on SIGTERM"
        return Processes(emu_status, lc_status, url, problem)
    finally:
        for child in children[1:]:  # LinuxCNC and its programs: a process group
            if child.poll() is None:
                os.killpg(child.pid, signal.SIGKILL)
        reap(children)
        for d in children_dirs:
            shutil.rmtree(d, ignore_errors=True)


# -- what the session recorded -------------------------------------------------------------

@dataclass(frozen=True)
class FollowingError:
    """One joint's following error in a session, joint units (mm, deg).

    Attributes:
        linuxcnc_max: LinuxCNC's own (``joint.N.f-error``, every servo period while the
            machine was enabled, and the period it was disabled in), largest magnitude.
        linuxcnc_limit: ``joint.N.f-error-lim`` at that period (FERROR scaled by the speed,
            at least MIN_FERROR).
        drive_max: the drive's, as the emulator recorded it: its position target less its
            encoder, every PWM period in OPERATION ENABLED, largest magnitude (NaN: no such
            period).
    """
    linuxcnc_max: float
    linuxcnc_limit: float
    drive_max: float

    @property
    def share(self) -> float:
        """linuxcnc_max over linuxcnc_limit (1 or more: LinuxCNC's protection tripped)."""
        return self.linuxcnc_max / self.linuxcnc_limit if self.linuxcnc_limit > 0 else math.nan


def read_samples(path: Path, joints: int) -> np.ndarray:
    """halsampler's file as rows of samples (one per servo period) by columns: each joint's
    f-error, each joint's f-error-lim, then :data:`SAMPLED`; shape (periods, 2 * joints +
    4), float64 (none: the file is missing or has no whole line)."""
    width = 2 * joints + len(SAMPLED)
    rows = []
    try:
        with open(path) as f:
            for line in f:
                values = line.split()
                if len(values) == width:  # a last line cut short is left out
                    rows.append([float(v) for v in values])
    except OSError:
        pass
    return np.array(rows, dtype=np.float64).reshape(-1, width)


def linuxcnc_ferror(samples: np.ndarray, joints: int) -> list[tuple[float, float]]:
    """(largest |f-error|, its limit there) per joint from :func:`read_samples`' rows
    (empty: no sample while enabled)."""
    a = samples
    if not a.size:
        return []
    enabled = a[:, 2 * joints] > 0.5
    # the period LinuxCNC disabled the machine in holds the error that tripped it
    judged = enabled | np.concatenate(([False], enabled[:-1]))
    if not judged.any():
        return []
    out = []
    for j in range(joints):
        e = np.abs(a[judged, j])
        k = int(np.argmax(e))
        out.append((float(e[k]), float(a[judged, joints + j][k])))
    return out


@dataclass(frozen=True)
class ServoTiming:
    """LinuxCNC's servo thread as the feeddrive component saw it while the machine was on
    (:func:`servo_timing`).

    ``jitter_us`` is each period's distance from the nominal one.  A thread woken ``L``
    late on an absolute deadline runs one period ``L`` long and the next ``L`` short, so
    its largest jitter is its largest wake-up latency, the figure cyclictest gives.

    Attributes:
        nominal_us: the servo period the INI asks for, µs.
        periods: periods measured (the first read has none before it).
        span_s: their total, s.
        period_us: the periods as they ran, µs.
        jitter_us: ``|period - nominal|``, µs.
        stale_periods: periods that found no new feedback from the emulator.
        feedback_frames: datagrams the component received over the span.
    """
    nominal_us: float
    periods: int
    span_s: float
    period_us: Percentiles
    jitter_us: Percentiles
    stale_periods: int
    feedback_frames: int

    @property
    def setpoints_per_s(self) -> float:
        """Setpoint datagrams sent per second (one per period)."""
        return self.periods / self.span_s if self.span_s > 0 else math.nan

    @property
    def feedback_per_s(self) -> float:
        """Feedback datagrams received per second."""
        return self.feedback_frames / self.span_s if self.span_s > 0 else math.nan

    def as_dict(self) -> dict:
        return {"nominal_us": self.nominal_us, "periods": self.periods, "span_s": self.span_s,
                "period_us": self.period_us.as_dict(), "jitter_us": self.jitter_us.as_dict(),
                "stale_periods": self.stale_periods, "feedback_frames": self.feedback_frames,
                "setpoints_per_s": self.setpoints_per_s,
                "feedback_per_s": self.feedback_per_s}

    def line(self) -> str:
        """One line for a person."""
        return (f"LinuxCNC's servo thread ({self.nominal_us:g} µs): {self.periods} periods, "
                f"jitter p50 {self.jitter_us.p50:.1f}, p99.9 {self.jitter_us.p999:.1f}, max "
                f"{self.jitter_us.max:.1f} µs; {self.stale_periods} periods without a new "
                f"feedback; {self.setpoints_per_s:.0f} setpoints and "
                f"{self.feedback_per_s:.0f} feedbacks per second")


def servo_timing(samples: np.ndarray, joints: int, nominal_ns: int) -> ServoTiming | None:
    """The servo thread's timing from :func:`read_samples`' rows while the machine was on
    (after LinuxCNC's start, with its threads at the session's priority: what a program
    runs under); None: no such period measured."""
    base = 2 * joints
    if not samples.size:
        return None
    period_ns = samples[:, base + 1]
    judged = (samples[:, base] > 0.5) & (period_ns > 0)
    if not judged.any():
        return None
    measured = period_ns[judged]
    stale, rx = (np.diff(samples[:, base + k], prepend=samples[0, base + k])[judged]
                 for k in (2, 3))
    return ServoTiming(
        nominal_us=nominal_ns / 1e3, periods=int(measured.size),
        span_s=float(measured.sum()) / 1e9,
        period_us=Percentiles.of_ns_in_us(measured),
        jitter_us=Percentiles.of_ns_in_us(np.abs(measured - nominal_ns)),
        stale_periods=int(stale.sum()), feedback_frames=int(rx.sum()))


def drive_ferror(run_dir: Path, names: tuple[str, ...], scales: tuple[float, ...]
                 ) -> list[float]:
    """Per axis the largest |position target - encoder| in OPERATION ENABLED, joint units
    (NaN when the recording cannot be read or has no such tick)."""
    try:
        cols = Recording(run_dir).read()
    except (RecordingError, OSError):
        return [math.nan] * len(names)
    out = []
    for name, scale in zip(names, scales):
        on = cols[f"{name}_drive_state"] == OPERATION_ENABLED
        err = cols[f"{name}_sp_target_position_counts"][on] - cols[
            f"{name}_plant_encoder_counts"][on]
        out.append(float(np.abs(err).max()) / abs(scale) if err.size else math.nan)
    return out
