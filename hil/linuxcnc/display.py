#!/usr/bin/python3
"""The headless DISPLAY program ``hil linuxcnc`` gives LinuxCNC: machine on, home, run a
program, and write what happened as JSON.

LinuxCNC starts it as ``display.py -ini INIFILE`` (``[DISPLAY] DISPLAY`` of the run's copy
of the INI names it); it runs in LinuxCNC's Python (the ``linuxcnc`` and ``hal`` modules of
LinuxCNC 2.9), not in feeddrive-hil's, so it imports nothing of the project.  When it
exits, LinuxCNC shuts down.

Its settings are in ``display.json`` beside it: ``result`` (the JSON written), ``program``
(G-code, or null), ``ferror`` (where halsampler writes every servo period's sample of the
run's sampler: each joint's following error and its limit, the machine's enable, the
servo thread's period), ``timeout_s`` (the longest a phase may take), ``servo_priority``
(the SCHED_FIFO priority its real-time threads are raised to before the machine is turned
on, or null; see :func:`raise_realtime_threads`).

The JSON: ``phases`` (each phase reached and its duration, s: ``on``, ``homed``,
``program``), ``errors`` (LinuxCNC's error and operator messages, in order), ``joints``
(per joint after homing: the feeddrive pins ``counts``, ``index-counts``, ``pos-fb`` and
LinuxCNC's ``position`` and ``homed``; at the end ``ferror_highmark``), ``completed`` (the
program ran to its end), ``failed`` (why a phase did not end, or null), ``fifo_threads``
and ``rt_cpus`` (the real-time threads raised, and the CPUs they may run on).
"""

import json
import os
import signal
import subprocess
import sys
import time

import hal
import linuxcnc

POLL_S = 0.02


SETTINGS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "display.json")


def raise_realtime_threads(priority: int) -> list:
    """Put the threads of this LinuxCNC's ``rtapi_app`` (the one whose RTAPI_FIFO_PATH is
    ours) other than its main thread under SCHED_FIFO ``priority``; the thread ids raised.

    Without a PREEMPT_RT kernel LinuxCNC runs its servo thread as an ordinary thread (POSIX
    non-realtime): on a busy machine it wakes milliseconds late now and then, and runs the
    periods it missed back to back.  Meanwhile the drives hold their last position target
    and speed feed-forward, so an axis runs on past the target by the speed times the
    delay, which LinuxCNC then sees as a following error.  Under SCHED_FIFO the thread
    wakes on time as the emulator's loop does (the kernel's timer latency, not PREEMPT_RT's
    bounds)."""
    fifo = os.environ.get("RTAPI_FIFO_PATH", "").encode()
    raised = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/comm") as f:
                if f.read().strip() != "rtapi_app":
                    continue
            with open(f"/proc/{pid}/environ", "rb") as f:
                if b"RTAPI_FIFO_PATH=" + fifo + b"\0" not in f.read():
                    continue
            for tid in os.listdir(f"/proc/{pid}/task"):
                if tid != pid:
                    os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
                    raised.append(int(tid))
        except OSError:  # gone meanwhile, or not permitted: it stays as LinuxCNC made it
            continue
    return raised


def thread_cpus(tids: list) -> list:
    """The CPUs any of the threads ``tids`` may run on, ascending (LinuxCNC pins its
    real-time threads to one; a thread gone meanwhile is left out)."""
    cpus = set()
    for tid in tids:
        try:
            cpus |= os.sched_getaffinity(tid)
        except OSError:
            continue
    return sorted(cpus)


class Run:
    def __init__(self, settings: dict):
        self.settings = settings
        self.timeout_s = float(settings["timeout_s"])
        self.cmd = linuxcnc.command()
        self.stat = linuxcnc.stat()
        self.errors = linuxcnc.error_channel()
        self.result = {"phases": {}, "errors": [], "joints": [], "completed": False,
                       "failed": None, "fifo_threads": [], "rt_cpus": []}
        self.t0 = time.monotonic()

    def drain_errors(self) -> None:
        while True:
            message = self.errors.poll()
            if not message:
                return
            kind, text = message
            self.result["errors"].append({"kind": kind, "text": text,
                                          "t_s": round(time.monotonic() - self.t0, 3)})

    def wait(self, what: str, done) -> bool:
        """Poll until ``done(stat)``; False (and ``failed`` said) on a timeout, or when
        LinuxCNC reported an error meanwhile."""
        start = time.monotonic()
        n_errors = len(self.result["errors"])
        while time.monotonic() - start < self.timeout_s:
            self.stat.poll()
            self.drain_errors()
            if len(self.result["errors"]) > n_errors and any(
                    e["kind"] in (linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR)
                    for e in self.result["errors"][n_errors:]):
                self.result["failed"] = f"{what}: LinuxCNC reported an error"
                return False
            if done(self.stat):
                self.result["phases"][what] = round(time.monotonic() - start, 3)
                return True
            time.sleep(POLL_S)
        self.result["failed"] = f"{what}: not done in {self.timeout_s:g} s"
        return False

    def joints(self) -> list:
        n = self.stat.joints
        return [{"counts": hal.get_value(f"feeddrive.{j}.counts"),
                 "index_counts": hal.get_value(f"feeddrive.{j}.index-counts"),
                 "pos_fb": hal.get_value(f"feeddrive.{j}.pos-fb"),
                 "position": self.stat.joint[j]["input"],
                 "homed": bool(self.stat.homed[j])} for j in range(n)]

    def go(self) -> None:
        c, s = self.cmd, self.stat
        if not self.wait("ready", lambda st: st.task_state == linuxcnc.STATE_ESTOP):
            return
        if self.settings["servo_priority"] is not None:
            self.result["fifo_threads"] = raise_realtime_threads(
                self.settings["servo_priority"])
            self.result["rt_cpus"] = thread_cpus(self.result["fifo_threads"])
        c.state(linuxcnc.STATE_ESTOP_RESET)
        if not self.wait("reset", lambda st: st.task_state == linuxcnc.STATE_ESTOP_RESET):
            return
        c.state(linuxcnc.STATE_ON)
        if not self.wait("on", lambda st: st.task_state == linuxcnc.STATE_ON):
            return
        c.mode(linuxcnc.MODE_MANUAL)
        c.teleop_enable(0)
        c.home(-1)
        if not self.wait("homed", lambda st: all(st.homed[j] for j in range(st.joints))
                         and st.inpos):
            return
        self.result["joints"] = self.joints()
        program = self.settings["program"]
        if program:
            c.teleop_enable(1)
            c.mode(linuxcnc.MODE_AUTO)
            c.wait_complete()
            c.program_open(program)
            c.auto(linuxcnc.AUTO_RUN, 0)
            if not self.wait("started", lambda st: st.interp_state != linuxcnc.INTERP_IDLE):
                return
            if not self.wait("program", lambda st: st.interp_state == linuxcnc.INTERP_IDLE):
                return
            self.result["completed"] = s.task_state == linuxcnc.STATE_ON
        s.poll()
        for j, joint in enumerate(self.result["joints"]):
            joint["ferror_highmark"] = s.joint[j]["ferror_highmark"]

    def finish(self) -> None:
        self.drain_errors()
        self.cmd.state(linuxcnc.STATE_OFF)
        self.cmd.state(linuxcnc.STATE_ESTOP)
        with open(self.settings["result"], "w") as f:
            json.dump(self.result, f, indent=1)


def main() -> int:
    with open(SETTINGS) as f:
        settings = json.load(f)
    # every joint's following error, each servo period (sampler.0 in the run's HAL)
    with open(settings["ferror"], "w") as out:
        sampler = subprocess.Popen(["halsampler", "-c", "0"], stdout=out)
    component = hal.component("hil-display")  # hal.get_value needs a component
    component.ready()
    run = Run(settings)
    try:
        run.go()
    except Exception as e:  # written into the result, which hil linuxcnc reads
        run.result["failed"] = f"the display program failed: {e!r}"
        raise
    finally:
        sampler.send_signal(signal.SIGTERM)
        sampler.wait(timeout=5)
        run.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
