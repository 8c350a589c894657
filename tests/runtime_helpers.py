"""What the runtime and loopback tests share: a machine-file variant two Python loops keep
up with, and child processes that are always reaped.

Every wait is bounded; every child started through :class:`Children` is killed and reaped
when the block ends, and the block checks that none is left running.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from hil.cia402 import EnableSequencer, State, statusword_state
from hil.extras import EXTRA_OF_MODULE
from hil.runtime.demo import wait_ready
from hil.runtime.record_reader import Recording
from hil.runtime.run_folder import EVENTS, RECORDING
from hil.runtime.stream_file import META_KEY, UNCHECKED_FORMAT
from tests.conftest import CONFIGS, ROOT

ARROW = CONFIGS / "arrow500_x.toml"
#: the Arrow 500 X at 2 kHz PWM: the current-loop gain at the technical optimum for the
#: longer PWM delay (K_p = L / (3 T_pwm) = 0.0045 H / 1.5 ms = 3 V/A), the position and IPO
#: cycles kept at 2 ms and 4 ms, the speed gain halved for the 4x longer speed cycle
SLOW_2KHZ = {"pwm_frequency_hz": "2000.0", "kp_v_per_a": "3.0", "position_cycle_ratio": "4",
             "ipo_cycle_ratio": "8", "speed_kp_nms_per_rad": "0.6"}
#: ... at 1 kHz, for a CAN link whose SYNC comes every tick: one node's CST frames per SYNC
#: (SYNC, RPDO1, RPDO4 and three TPDOs: 620 bits at the worst) need more than the 500 bits
#: a 0.5 ms cycle holds at 1 Mbit/s.  Current-loop gain at the technical optimum for the
#: longer PWM delay (L / (3 T_pwm) = 1.5 V/A); position and IPO cycles kept at 2 and 4 ms.
SLOW_1KHZ = {**SLOW_2KHZ, "pwm_frequency_hz": "1000.0", "kp_v_per_a": "1.5",
             "position_cycle_ratio": "2", "ipo_cycle_ratio": "4"}
#: longest wait for a child's ready line (a cold numba cache compiles for ~10 s)
READY_S = 120.0
#: longest wait for a child to finish once it should
EXIT_S = 60.0
#: longest wait for one answer of an emulator in another process
ANSWER_S = 5.0


def machine_variant(path: Path, values: dict[str, str], source: Path = ARROW) -> Path:
    """``source`` with each ``key = value`` line of ``values`` replaced (each key must occur
    exactly once, at the start of a line); written to ``path``."""
    text = source.read_text()
    for key, value in values.items():
        text, n = re.subn(rf"^{key}\s*=\s*[^#\n]*", f"{key} = {value} ", text, flags=re.MULTILINE)
        assert n == 1, f"{source}: {key} found {n} times"
    path.write_text(text)
    return path


def python_module(module: str, *args) -> list[str]:
    return [sys.executable, "-m", module, *map(str, args)]


ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (
    str(ROOT), os.environ.get("PYTHONPATH"))))}
#: ENV as a core-only install (``pip install -e .``, the README's first command) sees it:
#: the optional extras' modules are missing (tests/core_only/sitecustomize.py)
CORE_ONLY_ENV = {**ENV, "PYTHONPATH": os.pathsep.join((str(ROOT / "tests" / "core_only"),
                                                       ENV["PYTHONPATH"])),
                 "HIL_TESTS_WITHOUT": ",".join(EXTRA_OF_MODULE)}


class Children:
    """Child processes of one test: started here, killed and reaped on leaving."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.procs: list[subprocess.Popen] = []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait(timeout=EXIT_S)
            if p.stdout is not None:
                p.stdout.close()
        assert all(p.returncode is not None for p in self.procs), "a child is still running"

    def start(self, name: str, argv: list[str], ready: bool = False,
              group: bool = False, env: dict[str, str] = ENV) -> subprocess.Popen:
        """Start ``argv`` with stderr (and stdout unless ``ready``) to ``<name>.log``; in
        a process group of its own (with its children) if ``group``; in ``env``."""
        with open(self.log_dir / f"{name}.log", "w") as log:
            proc = subprocess.Popen(argv, cwd=ROOT, env=env, text=True, stderr=log,
                                    stdout=subprocess.PIPE if ready else log,
                                    start_new_session=group)
        self.procs.append(proc)
        return proc

    def emulator(self, config: Path, url: str, run_dir: Path, *extra,
                 group: bool = False) -> tuple:
        """``hil run`` on ``config`` at ``url``; returns (process, URL served) once ready
        (``group``: see :meth:`start`)."""
        proc = self.start("emulator", python_module(
            "hil.runtime.emulator", config, "--adapter", url, "--record", run_dir, *extra),
            ready=True, group=group)
        return proc, wait_ready(proc, READY_S)

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text()


def terminate(proc: subprocess.Popen) -> int:
    """SIGTERM, then the exit status (bounded wait)."""
    proc.send_signal(signal.SIGTERM)
    return proc.wait(timeout=EXIT_S)


def reserve_held(pid: int) -> int:
    """Bytes allocated to the run-folder reserves process ``pid`` holds open: unlinked
    files once named ``.hil-run-reserve`` (hil.runtime.run_folder), found through
    ``/proc/PID/fd``; 0 when it holds none (or has ended)."""
    held = 0
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except FileNotFoundError:
        return 0
    for fd in fds:
        try:
            if os.readlink(fd).endswith("/.hil-run-reserve (deleted)"):
                held += os.stat(fd).st_blocks * 512
        except FileNotFoundError:  # closed meanwhile
            continue
    return held


def write_unchecked_recording(folder: Path, rows: int = 50) -> Path:
    """``folder`` as a run folder of format 'hil-recording 1' (no CRC anywhere, pyarrow's
    plain writer), written without a run: ``rows`` ticks of one column ``x_m`` rising from 0
    to 1 and no events; returns ``folder``."""
    meta = b'{"format": "%s", "period_ns": 125000, "axes": []}' % UNCHECKED_FORMAT.encode()
    table = pa.table({"tick": np.arange(rows), "x_m": np.linspace(0, 1, rows)})
    for name in (RECORDING, EVENTS):
        columns = table if name == RECORDING else pa.table({"tick": pa.array([], pa.int64())})
        schema = columns.schema.with_metadata({META_KEY: meta})
        with pa.ipc.new_stream(str(folder / name), schema) as w:
            for batch in columns.cast(schema).to_batches(max_chunksize=20):
                w.write_batch(batch)
    return folder


def batch_messages(path: Path) -> list[tuple[int, int, int]]:
    """(first byte, first byte of the body, end) of each record batch's message in the
    Arrow IPC stream ``path``, in order, as pyarrow's message reader finds them (the
    schema's message left out)."""
    from hil.runtime.arrow import pa
    source = pa.OSFile(str(path))
    messages, start = [], 0
    for message in pa.ipc.MessageReader.open_stream(source):
        end = source.tell()
        messages.append((start, end - message.body.size, end))
        start = end
    return messages[1:]


def read_run(run_dir: Path) -> tuple[dict, dict]:
    """``hil run``'s report.json and its recording's columns (name -> array)."""
    report = json.loads((run_dir / "report.json").read_text())
    return report, Recording(run_dir).read()


def machine_lockstep_traces(config: Path, program: Path, settle_s: float, folder: Path,
                            feedback_delay_ticks: int = 0) -> dict[str, Path]:
    """Each axis's trace.csv (in ``folder``) of the machine's lock-step simulation of
    ``program``, run ``settle_s`` past its end: what a loopback run is compared with."""
    from hil.controller.path import read_path_program
    from hil.sim import TRACE_METADATA, MachineLockStep, servo_trace_columns
    from hil.trace_file import write_trace
    from plant.machines import load_machine_set
    m = load_machine_set(config)
    ls = MachineLockStep(m, feedback_delay_ticks=feedback_delay_ticks)
    ls.enable()
    profiles = ls.ctrl.plan(read_path_program(program, m.names))
    ls.ctrl.run_profiles(profiles)
    res = ls.run(profiles[0].duration_s + settle_s)
    return {name: write_trace(folder / f"trace_{name}.csv", servo_trace_columns(
        res[name], ctrl.sec.position_cycle_ratio), TRACE_METADATA)
        for name, ctrl in zip(m.names, ls.ctrl.ctrls)}


def run_loopback_pair(config: Path, link: str, program: Path,
                      folder: Path) -> tuple[dict, dict] | str:
    """``hil run`` on ``link`` (pinned to the last CPU) and ``hil controller`` running
    ``program`` (on the first, where there are two), both on ``config``, in ``folder``:
    (the controller's summary, the emulator's report), or the controller's log when it
    gave up."""
    cpus = sorted(os.sched_getaffinity(0))
    pin = ["--cpu", cpus[0]] if len(cpus) > 1 else []
    with Children(folder) as children:
        emulator, served = children.emulator(config, link, folder / "emulator",
                                             "--cpu", cpus[-1])
        ctl = children.start("controller", python_module(
            "hil.runtime.controller_proc", config, "--adapter", served, "--program", program,
            "--out", folder / "controller", *pin))
        code = ctl.wait(timeout=EXIT_S)
        assert terminate(emulator) == 0, children.log("emulator")
        if code != 0:
            return children.log("controller")
    return (json.loads((folder / "controller" / "summary.json").read_text()),
            json.loads((folder / "emulator" / "report.json").read_text()))


def usable_loopback(config: Path, program: Path, tmp_path: Path, attempts: int,
                    min_clear: float, glitch_window_s: float = 0.0
                    ) -> tuple[Path, dict, dict, dict[str, np.ndarray]]:
    """Loopback runs over UDP (:func:`run_loopback_pair`), at most ``attempts``, until one
    has at least ``min_clear`` of every axis's trace rows clear of timing faults
    (:func:`hil.runtime.sync.settled_rows`); (its folder, summary, report, each axis's
    clear rows).  Fails the test, with each attempt's reason, when none has."""
    import pytest

    from hil.runtime.sync import settled_rows
    failures = []
    for attempt in range(1, attempts + 1):
        folder = tmp_path / f"attempt{attempt}"
        folder.mkdir()
        result = run_loopback_pair(config, "udp://127.0.0.1:0", program, folder)
        if isinstance(result, str):
            failures.append(f"attempt {attempt}: the controller gave up:\n{result[-600:]}")
            continue
        summary, report = result
        with np.load(folder / "controller" / "controller.npz") as npz:
            cols = {k: npz[k] for k in ("lag_ticks", "fb_time_s", "tick")}
        clear = {name: settled_rows(cols, axis["trace_every_ticks"],
                                    summary["period_ns"] * 1e-9,
                                    glitch_window_s=glitch_window_s)
                 for name, axis in summary["axes"].items()}
        if min(c.mean() for c in clear.values()) >= min_clear:
            return folder, summary, report, clear
        failures.append(f"attempt {attempt}: too few rows clear of timing faults; "
                        f"controller feedback: {summary['feedback']}")
    pytest.fail("no usable run:\n" + "\n".join(failures))


def exchange(ep, sp, fb, n: int, seq=None, iq: float = 0.0) -> None:
    """``n`` feedbacks, each answered at once by a setpoint (controlword from ``seq``)."""
    for _ in range(n):
        assert ep.recv_feedback(fb, ANSWER_S), "the emulator stopped answering"
        sp.seq += 1
        if seq is not None:
            sp.controlword = seq.next_controlword(fb.statusword)
        sp.iq_ref_a = iq
        ep.send_setpoint(sp)


#: feedbacks the enable sequence may take (0.2 s at 2 kHz)
ENABLE_CYCLES = 400


def enable(ep, sp, fb) -> EnableSequencer:
    """The CiA 402 enable sequence (a fault reset first if the drive is in FAULT) over
    ``ep``, answering each feedback; the sequencer once OPERATION ENABLED.  The budget,
    ENABLE_CYCLES feedbacks, covers a backlog of stale feedback datagrams queued while a
    loaded machine held this process off the CPU (50 were not enough under load)."""
    seq = EnableSequencer(timeout_cycles=ENABLE_CYCLES)
    seq.enable()
    exchange(ep, sp, fb, 1, seq)
    for _ in range(ENABLE_CYCLES):
        exchange(ep, sp, fb, 1, seq)
        if seq.done:
            return seq
    raise AssertionError(seq.reason)


def until_state(ep, sp, fb, state: State, limit: int = 4000) -> None:
    """Answer feedback until the drive reports ``state``."""
    for _ in range(limit):
        exchange(ep, sp, fb, 1)
        if statusword_state(fb.statusword) == state:
            return
    raise AssertionError(f"drive not in {state.name}: 0x{fb.statusword:04X}")


def end_stop_reach(drive, arrival_speed: float) -> float:
    """How far (m) the table of ``drive``'s plant may be inside an end stop, a stiff
    contact: what the motor's peak force presses, plus what the whole drive train
    compresses arriving at ``arrival_speed`` (motor units/s; an undamped contact,
    v sqrt(m / k)).  An axis braked at the stop arrives at about its standstill speed;
    arriving at speed is a failure of the drive's protection."""
    from plant.assemble import reflected_inertia
    plant = drive.plant
    cfg, ratio, k = plant.config, plant.built.ratio, plant.built.end_stops.stiffness
    peak_n = cfg.motor.torque_constant_nm_per_a * cfg.motor.current_max_a / ratio
    mass = reflected_inertia(cfg) / ratio ** 2
    return (peak_n + arrival_speed * ratio * np.sqrt(k * mass)) / k


def check_recording(run_dir: Path) -> tuple[dict, dict]:
    """The run's report and recording, with what must hold whatever happened: the plant
    state finite, every setpoint applied finite and within the power stage, the table
    inside the stroke and its end stops."""
    report, rec = read_run(run_dir)
    from hil.drive.core import EmulatedDrive
    from plant import Plant
    from plant.config import load_machine
    cfg = load_machine(report["machine_file"])
    table = cfg.table
    for name in ("plant_table_pos", "plant_motor_vel", "plant_iq_a"):
        assert np.isfinite(rec[name]).all(), name
    for name in ("sp_iq_ref_a", "sp_uq_v", "sp_target_position_counts"):
        assert np.isfinite(rec[name]).all(), f"{name}: a refused value was applied"
    assert (np.abs(rec["sp_iq_ref_a"]) <= 28.0).all()
    x = rec["plant_table_pos"]
    drive = EmulatedDrive(Plant(cfg))
    over = table.end_stop_overtravel_m + end_stop_reach(drive, 10.0 * drive.monitor.standstill())
    assert -over < x.min() and x.max() < table.travel_m + over, (x.min(), x.max(), over)
    return report, rec


def wait_for_enabled(run, ctl) -> None:
    """Until the run's recording has a row with the drive in OPERATION ENABLED (bounded;
    fails if the controller ends first)."""
    end = time.monotonic() + READY_S
    while time.monotonic() < end:
        assert ctl.poll() is None, "the controller ended before the drive was enabled"
        try:
            state = Recording(run).read(["drive_state"])["drive_state"]
        except (OSError, ValueError):  # not there yet, or a batch being written
            state = ()
        if int(State.OPERATION_ENABLED) in state:
            return
        time.sleep(0.1)
    pytest.fail("the drive was not enabled within READY_S")
