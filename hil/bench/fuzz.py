"""``hil bench fuzz``: every setpoint decoder fed N frames through its real endpoint into
emulated drives, with the checks that say the drive protects itself.

::

    python3 -m hil.bench.fuzz --frames 100000 [--seed N] [--json] [--decoder NAME ...]

Decoders (:mod:`hil.bench.fuzz_links`): ``udp-v1`` and ``udp-v2`` (msgpack datagrams on
127.0.0.1, one axis and two), ``serial`` (msgpack in serial frames over an ``os.openpty``
pair), ``can-rpdo`` and ``can-sdo`` (a CiA 402 node on python-can's ``virtual`` bus).
Behind each endpoint one :class:`~hil.drive.EmulatedDrive` of the Arrow 500 X
(configs/arrow500_x.toml) per axis, started at mid travel and cycled once per frame (one
PWM period), as the emulator's loop does: a setpoint the endpoint refused faults its
drive.  A master enables the drives with the CiA 402 sequence and, after every fault,
resets and enables them again, so that faults keep coming; the frames are its valid
setpoints and mutations of them (:mod:`hil.bench.fuzz_frames`, numpy's generator seeded
with ``--seed``).

Per decoder: the frames sent, the endpoint's counters, the drive faults by error code
603Fh, the fault resets that succeeded (FAULT left by transition 15), the deepest
penetration of a stop, and the checks, each PASS or FAIL:

* **nothing raised** out of the endpoint or the drive;
* **records within bounds**: after every frame each field of every axis's setpoint record
  is finite and within the drive's SetpointBounds, its mode one the drive takes;
* **plant finite**: every plant state variable finite after every cycle;
* **table within the stroke bound**: the table between the stops (``[table]
  end_stop_overtravel_m`` beyond the travel) widened by the penetration of the stall force
  F = K_t I_max / ratio at rest, F/k (k the stop's stiffness): the drive stops the axis
  before it hits a stop at speed.  On ``can-sdo`` the master writes the drive's parameter
  objects too (a slow quick stop 6085h, software limits 607Dh beyond the stops, a fault
  reaction 605Eh of 0 that lets the axis coast), so an impact is the master's doing
  there: the bound adds v sqrt(M/k) for an impact at v, the fastest table speed seen (M
  every inertia the motor moves, at the table: rigid-body energy, F x + M v^2 / 2 >=
  k x^2 / 2), and only says the plant stays physical;
* **counters add up**: per frame, as :mod:`hil.bench.fuzz_links` says for its transport;
* **refusals fault the drive**: the feedback of the cycle that met a refused setpoint
  carries a non-zero 603Fh (a refused SDO write is answered by its abort alone).

The exit status is 1 when a check fails.  Progress goes to stderr: one updating line on
a terminal, a line per tenth when piped.  ``hil bench fuzz`` takes the same options
(:func:`add_arguments`, :func:`run_from_args`).
"""

import argparse
import json
import math
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from hil.bench.fuzz_frames import AxisLimits
from hil.bench.fuzz_links import LINKS
from hil.cia402 import EnableSequencer, State
from hil.controller.config import motor_constant
from hil.drive import DriveSet, EmulatedDrive
from io_adapters.messages import axis_records, message_pair
from plant import Plant
from plant import layout as L
from plant.assemble import reflected_inertia
from plant.config import load_machine

ARROW = Path(__file__).resolve().parents[2] / "configs" / "arrow500_x.toml"
DECODERS = tuple(LINKS)
CHECKS = ("nothing raised", "records within bounds", "plant finite",
          "table within the stroke bound", "counters add up", "refusals fault the drive")
#: where the tables start, a share of the travel
START_SHARE = 0.5
FLOAT_FIELDS = ("target_position_counts", "target_velocity_counts_s",
                "velocity_offset_counts_s", "iq_ref_a", "id_ref_a", "ud_v", "uq_v")
BOUND_OF = ("position_counts", "velocity_counts_s", "velocity_counts_s", "current_a",
            "current_a", "voltage_v", "voltage_v")


class Checks:
    """The checks of one decoder: the first failure of each, in words."""

    def __init__(self):
        self.failures: dict[str, str] = {}

    def fail(self, name: str, detail: str) -> None:
        self.failures.setdefault(name, detail)

    def as_dict(self) -> dict[str, str]:
        return {name: "FAIL" if name in self.failures else "PASS" for name in CHECKS}


class Stroke:
    """One table's stops and the stroke bound of the module docstring (m); ``impacts``:
    the master may set the drive's braking, so an impact is allowed for."""

    def __init__(self, plant: Plant, impacts: bool):
        cfg, stops = plant.config, plant.built.end_stops
        stall_n = motor_constant(cfg) * cfg.motor.current_max_a / plant.built.ratio
        self.stop_neg, self.stop_pos = stops.stop_neg, stops.stop_pos
        self.static_m = stall_n / stops.stiffness
        self.impact_m_per_m_s = math.sqrt(reflected_inertia(cfg) / plant.built.ratio ** 2
                                          / stops.stiffness) if impacts else 0.0
        self.v_max = 0.0
        self.deepest_m = 0.0

    def as_dict(self) -> dict:
        """The stops, the bound's parts and the deepest penetration (of the first axis)."""
        return {"stops_m": [self.stop_neg, self.stop_pos], "static_penetration_m": self.static_m,
                "impact_allowed": self.impact_m_per_m_s > 0.0,
                "fastest_table_speed_m_s": self.v_max, "deepest_penetration_m": self.deepest_m}

    def holds(self, x: float, v: float) -> bool:
        """Whether the table at ``x`` (m) moving at ``v`` (m/s) is within the bound."""
        self.v_max = max(self.v_max, abs(v))
        beyond = max(self.stop_neg - x, x - self.stop_pos)
        self.deepest_m = max(self.deepest_m, beyond)
        return beyond <= self.static_m + self.v_max * self.impact_m_per_m_s


def record_within(sp, bounds) -> bool:
    """Every float of ``sp`` finite and within ``bounds``, its mode one of them (the
    rules of SetpointBounds, field by field)."""
    return sp.mode in bounds.modes and all(
        abs(getattr(sp, name)) <= getattr(bounds, bound)  # False for NaN
        for name, bound in zip(FLOAT_FIELDS, BOUND_OF)) and all(
        math.isfinite(getattr(sp, name)) for name in FLOAT_FIELDS)


class Axes:
    """The drives behind one endpoint, their master and what the checks need.

    Args:
        n_axes: Arrow 500 X axes, each its own plant and drive.
        impacts: the master may write the drive's braking parameters (:class:`Stroke`).

    Attributes:
        sp, fb: the setpoint the endpoint fills and the feedback the drives write.
        bounds, limits: each drive's SetpointBounds and the master's AxisLimits.
        faults: drive faults by 603Fh; resets: fault resets that succeeded.
    """

    def __init__(self, n_axes: int, impacts: bool):
        cfg = load_machine(ARROW)
        self.plants = [Plant(cfg, table_pos=START_SHARE * cfg.table.travel_m)
                       for _ in range(n_axes)]
        self.drives = DriveSet([EmulatedDrive(p) for p in self.plants])
        self.sp, self.fb = message_pair(n_axes)
        self.bounds = tuple(d.setpoint_bounds() for d in self.drives.drives)
        self.limits = [AxisLimits(current_a=cfg.motor.current_max_a,
                                  speed_counts_s=d.params.max_speed / d.rad_per_count,
                                  counts_per_mm=1e-3 / p.built.ratio / d.rad_per_count)
                       for p, d in zip(self.plants, self.drives.drives)]
        self.strokes = [Stroke(p, impacts) for p in self.plants]
        self.sequencers = [EnableSequencer(timeout_cycles=2**62) for _ in range(n_axes)]
        self.faults: Counter = Counter()
        self.resets = 0
        self._codes = [0] * n_axes
        self._states = [State.SWITCH_ON_DISABLED] * n_axes

    def controlwords(self) -> list[int]:
        """The master's controlword of each axis: enabling, and after a fault (the
        sequencer failed when its drive left OPERATION ENABLED) resetting and enabling
        again."""
        words = []
        for seq, fb in zip(self.sequencers, axis_records(self.fb)):
            if seq.failed or seq.target != State.OPERATION_ENABLED:
                seq.enable()
            words.append(seq.next_controlword(fb.statusword))
        return words

    def counts(self) -> list[float]:
        """Each axis's position actual, motor-encoder increments."""
        return [p.out[L.O_ENCODER] for p in self.plants]

    def cycle(self, refused: int, checks: Checks) -> None:
        """Fault the drives whose setpoint was refused (bit mask ``refused``), cycle every
        drive once, check."""
        drives = self.drives.drives
        for a, d in enumerate(drives):
            if refused >> a & 1:
                d.refuse_setpoint()
        self.drives.cycle(self.sp, self.fb)
        for a, (d, sp, fb) in enumerate(zip(drives, axis_records(self.sp),
                                            axis_records(self.fb))):
            plant = d.plant
            if not record_within(sp, self.bounds[a]):
                checks.fail("records within bounds", f"axis {a}: {sp}")
            if refused >> a & 1 and fb.fault == 0:
                checks.fail("refusals fault the drive", f"axis {a}: 603Fh 0 after a refusal")
            if not np.isfinite(plant.state).all():
                checks.fail("plant finite", f"axis {a}: {plant.state}")
            x, v = plant.out[L.O_TABLE_POS], plant.out[L.O_TABLE_VEL]
            if not self.strokes[a].holds(x, v):
                checks.fail("table within the stroke bound", f"axis {a}: table at {x} m "
                            f"moving at {v} m/s")
            if fb.fault and not self._codes[a]:
                self.faults[f"{fb.fault:04X}h"] += 1
            state = d.sm.state
            if self._states[a] == State.FAULT and state != State.FAULT:
                self.resets += 1
            self._codes[a], self._states[a] = fb.fault, state


class Progress:
    """Frames done on stderr: one updating line on a terminal, a line per tenth when piped."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()

    def __call__(self, decoder: str, done: int, total: int, seconds: float) -> None:
        step = max(1, total // (100 if self.tty else 10))
        if done % step and done != total:
            return
        line = f"{decoder}: {done}/{total} frames, {seconds:.1f} s"
        if self.tty:
            end = "\n" if done == total else ""
            self.stream.write(f"\r{line:<60}{end}")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def run_decoder(decoder: str, frames: int, seed: np.random.SeedSequence,
                progress=lambda *args: None) -> dict:
    """``frames`` frames through ``decoder``; its JSON-ready row (module docstring)."""
    link_type, n_axes = LINKS[decoder]
    axes, checks = Axes(n_axes, link_type.WRITES_PARAMETERS), Checks()
    start = time.perf_counter()
    link = None
    try:
        link = link_type(np.random.default_rng(seed), axes)
        for done in range(1, frames + 1):
            link.feed(axes, checks)
            axes.cycle(link.endpoint.refused_axes, checks)
            progress(decoder, done, frames, time.perf_counter() - start)
    except Exception as e:  # noqa: BLE001 -- whatever it is, it is the finding: report it
        checks.fail("nothing raised", f"{type(e).__name__}: {e}")
    finally:
        if link is not None:
            link.close()
    return {"decoder": decoder, "frames": frames, "seconds": time.perf_counter() - start,
            "counters": {} if link is None else link.counters(),
            "faults": dict(sorted(axes.faults.items())),
            "fault_resets": axes.resets, "stroke": axes.strokes[0].as_dict(),
            "checks": checks.as_dict(), "failures": checks.failures}


def run(frames: int, seed: int, decoders: tuple[str, ...] = DECODERS,
        progress=lambda *args: None) -> dict:
    """Every decoder of ``decoders``, ``frames`` frames each (each decoder's generator is
    seeded from ``seed`` and its name's position in :data:`DECODERS`, so that one decoder
    alone gives the frames it gives in a full run)."""
    if frames < 1:
        raise ValueError(f"--frames must be >= 1, got {frames}")
    seeds = np.random.SeedSequence(seed).spawn(len(DECODERS))
    rows = [run_decoder(d, frames, seeds[DECODERS.index(d)], progress) for d in decoders]
    return {"command": "hil bench fuzz", "seed": seed, "frames_per_decoder": frames,
            "machine_file": str(ARROW), "decoders": rows,
            "ok": all(set(r["checks"].values()) == {"PASS"} for r in rows)}


def text(report: dict) -> str:
    """The report for a person: per decoder its counters, faults and checks."""
    lines = [(f"hil bench fuzz: {report['frames_per_decoder']} frames per decoder, seed "
              f"{report['seed']}, {Path(report['machine_file']).name}")]
    for r in report["decoders"]:
        counters = ", ".join(f"{k} {v}" for k, v in r["counters"].items()
                             if not isinstance(v, dict))
        faults = ", ".join(f"{k} {v}" for k, v in r["faults"].items()) or "none"
        lines += [f"{r['decoder']}: {r['frames']} frames in {r['seconds']:.1f} s",
                  f"  counters: {counters}"]
        for name, counts in r["counters"].items():
            if isinstance(counts, dict):
                lines.append(f"  {name}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
        stroke = r["stroke"]
        impacts = ", impacts allowed" if stroke["impact_allowed"] else ""
        lines += [f"  drive faults by 603Fh: {faults}; fault resets that succeeded: "
                  + str(r["fault_resets"]),
                  f"  deepest penetration of a stop {stroke['deepest_penetration_m'] * 1e6:.3g} "
                  + f"µm (F/k {stroke['static_penetration_m'] * 1e6:.3g} µm{impacts}); "
                  + f"fastest table {stroke['fastest_table_speed_m_s']:.3g} m/s",
                  "  checks: " + ", ".join(f"{k} {v}" for k, v in r["checks"].items())]
        lines += [f"  FAIL {name}: {detail}" for name, detail in r["failures"].items()]
    lines.append("all checks PASS" if report["ok"] else "some checks FAIL")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hil bench fuzz``."""
    p.add_argument("--frames", type=int, default=100000, metavar="N",
                   help="frames per decoder (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="numpy seed (default %(default)s)")
    p.add_argument("--decoder", action="append", choices=DECODERS,
                   help="only this decoder (repeatable; default: all)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def run_from_args(args: argparse.Namespace) -> int:
    """``hil bench fuzz``: run, print the report; 1 if a check failed, 2 on bad input."""
    try:
        report = run(args.frames, args.seed, tuple(args.decoder or DECODERS), Progress())
    except ValueError as e:
        print(f"hil bench fuzz: {e}", file=sys.stderr)
        return 2
    print(json.dumps(report, indent=1) if args.json else text(report))
    return 0 if report["ok"] else 1


def main(argv: list[str] | None = None) -> int:
    """``python3 -m hil.bench.fuzz ...``: the same as ``hil bench fuzz ...``."""
    parser = argparse.ArgumentParser(prog="hil bench fuzz", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
