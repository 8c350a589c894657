"""The timing cost of a real-time run: the lock-step simulation against the replay of the
real timing, with the late and missed setpoints that made the difference.

Three traces of one part program (one axis): the **lock-step** simulation (``hil sim``:
controller tick k's setpoint drives drive cycle k, and tick k+1 reads its feedback), the
**recording** of the real run (``hil run`` against ``hil controller``), and its
**replay** (:mod:`hil.replay.replay`: the plant re-run on exactly the setpoints the drive
applied each tick).  The replay is checked to equal the recording, so the plant added
nothing; what is left between lock-step and replay is the **timing cost**: setpoints that
reached the drive a tick or more late, or never (a newer one overtook them), and
feedback that reached the controller late (it extrapolates).

**Alignment of the traces.**  Servo-trace row i (a position-control cycle counted from
the program's start) is controller tick ``k_i`` in ``controller.npz``.  The drive tick
whose feedback that controller tick reads under lock-step timing is ``k_i + d``, where
``d`` is the median, over the ticks that read new feedback at lag 0, of (drive tick whose
``plant_time_s`` equals the feedback's ``fb_time_s``) - ``k``: the phase the controller's
alignment set.  The replay's actual position of row i is then the position measured
after drive tick ``k_i + d`` (``plant_scale_counts`` or ``plant_encoder_counts``
converted as the controller converts them), and its following error
``pos_set_i - pos_replay_i`` with the lock-step's ``pos_set_i`` (the interpolator does
not depend on timing).  The difference of the two following errors per row,
``dFE_i = FE_replay_i - FE_lockstep_i = pos_lockstep_i - pos_replay_i``, is the timing
cost.

**Late and missed setpoints**, from ``sp_seq``/``sp_new`` against ``tick``: the setpoint
``s`` is due at drive tick ``s + e``, with ``e`` the median of ``tick - sp_seq`` over the
program's ticks that received one.  Every ``s`` due in the program's window is *on time*
(first applied at its tick), *late* (first applied later; by how many ticks), *early*
(applied before its tick: the phase moved), or *missed* (never applied: a newer one was
taken first).  Ticks that received nothing held the previous setpoint.  Only setpoints
due on recorded ticks count (the recording has no row for a tick the skip policy dropped
or the recording's writer lost).

**Attribution, per run of them**: consecutive faulty setpoints (due on consecutive ticks)
form one run; the following-error difference a run caused is the largest ``|dFE|`` on
the rows from its first due tick up to the next run's first due tick (the loops carry a
disturbance until the next one starts; rows after the program's last run belong to it).
``clean_diff`` is the largest ``|dFE|`` before the first run: what the plant's noise
counter (the emulator's plant ran idle ticks before the controller came) and the
measurement's quantisation leave with perfect timing.

**Tolerance** (what the verdict checks the timing cost against), derived from this run's
measured transport:

* ``D = delay + jitter + controller lateness + emulator lateness``: the setpoint's one-way
  delay (``sp_rx_ns - sp_t_ns``, one host's clock on loopback) p50 plus its jitter
  (max - p50), plus the controller's worst lateness in the program (a late tick sends
  late) and the emulator's (a late drive tick falls behind the controller: the setpoints
  that come meanwhile are taken late or drained): the furthest the exchange of one tick
  moved from the lock-step's.
* A setpoint later than its tick is applied ``m = max(1, ceil(D / T))`` ticks late (T the
  period; any lateness past the deadline costs a whole tick).  Meanwhile the drive holds
  the previous target, at most ``v_max * m * T`` behind (``v_max`` the largest speed of
  the lock-step's commanded path ``pos_set``), and the controller, reading feedback ``m``
  ticks old, extrapolates it with the speed actual value, wrong by at most
  ``a_max (m T)^2 / 2`` (``a_max`` the path's largest acceleration).
* The position loop's answer to such a command error stays within twice it
  (:data:`LOOP_PEAK`: a loop overshooting by at most 100 %), and each trace measures
  position to one count of its measuring system (``resolution``), on both sides.

``tolerance = LOOP_PEAK * (v_max m T + a_max (m T)^2 / 2) + 2 * resolution``

A timing cost within it is what this run's transport can explain; beyond it, something
else differs between the real run and the lock-step simulation.
"""

import math
from dataclasses import asdict, dataclass

import numpy as np

from hil.controller.nc import Controller
from hil.trace_file import read_trace
from plant.config import MachineConfig

#: the position loop's largest answer to a command error, as a multiple of it
LOOP_PEAK = 2.0
#: late runs listed in full in the printed summary (all are in the JSON)
SHOWN_RUNS = 5
#: the offset (ticks) of a setpoint that was never applied
MISSED = 2 ** 31


class TimingError(ValueError):
    """The traces cannot be aligned; the message says which file and why."""


@dataclass(frozen=True)
class LateRun:
    """Consecutive late, early or missed setpoints and what they cost.

    Attributes:
        first_tick: the drive tick the first was due at.
        setpoints: how many in the run.
        late, early, missed: of which late, early, missed.
        worst_ticks: the most ticks one of them was late (0: none late).
        fe_diff: the largest |dFE| from its first tick to the next run's, m (rad rotary).
    """
    first_tick: int
    setpoints: int
    late: int
    early: int
    missed: int
    worst_ticks: int
    fe_diff: float


@dataclass(frozen=True)
class Tolerance:
    """The timing cost this run's transport can explain (see the module docstring); SI.

    Attributes:
        delay_s: the setpoints' one-way delay, p50.
        jitter_s: their max - p50.
        controller_lateness_s: the controller's worst lateness in the program.
        emulator_lateness_s: the emulator's worst lateness in the program.
        late_ticks: m.
        v_max, a_max: the largest speed and acceleration of the lock-step's commanded
            path (m/s, m/s²; rad/s, rad/s² rotary).
        resolution: one count of the position measurement (m or rad).
        value: the tolerance on max |dFE| (m or rad).
    """
    delay_s: float
    jitter_s: float
    controller_lateness_s: float
    emulator_lateness_s: float
    late_ticks: int
    v_max: float
    a_max: float
    resolution: float
    value: float


@dataclass(frozen=True)
class TimingCost:
    """Lock-step against the replay of the real timing (see the module docstring); SI
    positions (m, rad on a rotary table).

    Attributes:
        rows: servo-trace rows compared.
        fe_max_lockstep, fe_max_replay: the two following errors' largest magnitude.
        diff_max, diff_rms: of dFE over the rows.
        diff_max_t_s: program time of the largest |dFE|.
        clean_diff: the largest |dFE| before the first late run.
        setpoints: setpoints due in the program's window.
        on_time, late, early, missed: of them.
        held_ticks: ticks of the window that received no setpoint.
        runs: the late runs, in time order.
        tolerance: what the transport explains.
    """
    rows: int
    fe_max_lockstep: float
    fe_max_replay: float
    diff_max: float
    diff_rms: float
    diff_max_t_s: float
    clean_diff: float
    setpoints: int
    on_time: int
    late: int
    early: int
    missed: int
    held_ticks: int
    runs: tuple[LateRun, ...]
    tolerance: Tolerance

    @property
    def within(self) -> bool:
        """The timing cost is within the tolerance."""
        return self.diff_max <= self.tolerance.value

    def as_dict(self) -> dict:
        """JSON-ready (SI)."""
        return {**asdict(self), "within_tolerance": self.within}


def _measured_position(rec: dict, ctrl: Controller) -> np.ndarray:
    """The position the controller reads from each recorded tick's feedback (m or rad)."""
    if ctrl.scale_res:
        x = rec["plant_scale_counts"] * ctrl.scale_res
    else:
        x = rec["plant_encoder_counts"] * ctrl.rad_per_count * ctrl.ratio
    return ctrl.polarity * x


def _feedback_phase(rec: dict, npz: dict) -> int:
    """d: drive tick read - controller tick, on the ticks read at lock-step timing."""
    ok = (npz["fb_new"] == 1) & (npz["lag_ticks"] == 0)
    if not ok.any():
        raise TimingError("controller.npz: no tick read new feedback at lag 0; the traces "
                          "cannot be aligned")
    time_s = rec["plant_time_s"]
    j = np.clip(np.searchsorted(time_s, npz["fb_time_s"][ok]), 0, time_s.size - 1)
    exact = time_s[j] == npz["fb_time_s"][ok]
    if not exact.any():
        raise TimingError("no feedback time stamp of controller.npz is a recorded plant time")
    return int(np.median(rec["tick"][j[exact]] - npz["k"][ok][exact]))


def _setpoints(rec: dict, first: int, last: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Counts of the setpoints due in the recorded ticks first..last (a tick without a row
    -- dropped by the skip policy, or not recorded -- says nothing), and per faulty one its
    due tick and how late it came (ticks; > 0 late, < 0 early, :data:`MISSED`)."""
    tick = rec["tick"].astype(np.int64)
    seq = rec["sp_seq"].astype(np.int64)
    window = (tick >= first) & (tick <= last)
    new = window & (rec["sp_new"] == 1)
    if not new.any():
        raise TimingError(f"no setpoint received in drive ticks {first}..{last}")
    e = int(np.median(tick[new] - seq[new]))
    seqs, idx = np.unique(seq[new], return_index=True)
    applied = tick[new][idx]
    due_seq = tick[window] - e
    pos = np.clip(np.searchsorted(seqs, due_seq), 0, seqs.size - 1)
    found = seqs[pos] == due_seq
    offset = np.where(found, applied[pos] - (due_seq + e), MISSED)
    counts = {"setpoints": int(due_seq.size), "on_time": int((offset == 0).sum()),
              "late": int(((offset > 0) & (offset != MISSED)).sum()),
              "early": int((offset < 0).sum()), "missed": int((offset == MISSED).sum()),
              "held_ticks": int((window & (rec["sp_new"] == 0)).sum())}
    bad = offset != 0
    return counts, due_seq[bad] + e, offset[bad]


def _runs(due: np.ndarray, offset: np.ndarray, row_tick: np.ndarray,
          dfe: np.ndarray) -> tuple[LateRun, ...]:
    if due.size == 0:
        return ()
    breaks = np.flatnonzero(np.diff(due) > 1)
    starts, ends = np.r_[0, breaks + 1], np.r_[breaks, due.size - 1]
    runs = []
    for n, (a, b) in enumerate(zip(starts, ends)):
        off = offset[a:b + 1]
        until = due[starts[n + 1]] if n + 1 < starts.size else np.iinfo(np.int64).max
        rows = (row_tick >= due[a]) & (row_tick < until)
        late = off[(off > 0) & (off != MISSED)]
        runs.append(LateRun(int(due[a]), int(b - a + 1), int(late.size), int((off < 0).sum()),
                            int((off == MISSED).sum()), int(late.max()) if late.size else 0,
                            float(np.abs(dfe[rows]).max()) if rows.any() else 0.0))
    return tuple(runs)


def timing_cost(rec: dict, npz: dict, lockstep_trace, cfg: MachineConfig,
                period_s: float) -> TimingCost:
    """The timing cost of a run (see the module docstring).

    Args:
        rec: the recording's columns (tick, lateness_ns, sp_new, sp_seq, sp_t_ns,
            sp_rx_ns, plant_time_s, plant_scale_counts, plant_encoder_counts).
        npz: the controller's ``controller.npz`` columns (k, tick, fb_new, lag_ticks,
            fb_time_s, lateness_ns).
        lockstep_trace: the lock-step simulation's trace.csv.
        cfg: the machine file (one axis).
        period_s: the period of both loops, s.
    """
    ctrl = Controller(cfg, period_s)
    every = ctrl.sec.position_cycle_ratio
    rows_ctrl = np.flatnonzero(npz["tick"] % every == 0)
    ls = read_trace(lockstep_trace)
    pos_name, set_name = ls.resolve("pos_mm"), ls.resolve("pos_set_mm")
    pos_ls, pos_set = ls.si(pos_name), ls.si(set_name)
    n = min(rows_ctrl.size, pos_ls.size)
    if n == 0:
        raise TimingError(f"{lockstep_trace}: no row to compare with controller.npz")
    d = _feedback_phase(rec, npz)
    k_rows = npz["k"][rows_ctrl[:n]].astype(np.int64)
    read_tick = k_rows + d
    tick = rec["tick"].astype(np.int64)
    j = np.clip(np.searchsorted(tick, read_tick), 0, tick.size - 1)
    there = tick[j] == read_tick
    pos_replay = np.where(there, _measured_position(rec, ctrl)[j], np.nan)
    fe_ls = pos_set[:n] - pos_ls[:n]
    fe_replay = pos_set[:n] - pos_replay
    dfe = np.where(there, fe_replay - fe_ls, 0.0)
    # setpoints of the program: those the drive ticks read by the rows were driven by
    counts, due, offset = _setpoints(rec, int(read_tick[0]), int(read_tick[-1]))
    runs = _runs(due, offset, read_tick, dfe)
    first_run = runs[0].first_tick if runs else np.iinfo(np.int64).max
    clean = read_tick < first_run
    worst = int(np.argmax(np.abs(dfe)))
    tol = _tolerance(rec, npz, read_tick, ls, ctrl, period_s)
    return TimingCost(
        rows=int(there.sum()), fe_max_lockstep=float(np.abs(fe_ls).max()),
        fe_max_replay=float(np.nanmax(np.abs(fe_replay))),
        diff_max=float(np.abs(dfe).max()), diff_rms=float(np.sqrt(np.mean(dfe[there] ** 2))),
        diff_max_t_s=float(ls.column("t_s")[worst]),
        clean_diff=float(np.abs(dfe[clean]).max()) if clean.any() else 0.0,
        **counts, runs=runs, tolerance=tol)


def _tolerance(rec: dict, npz: dict, read_tick: np.ndarray, ls, ctrl: Controller,
               period_s: float) -> Tolerance:
    """The tolerance of the module docstring from the program's ticks (drive ticks
    ``read_tick[0]`` .. ``read_tick[-1]``, the controller's rows of ``npz``)."""
    tick = rec["tick"]
    program = (tick >= read_tick[0]) & (tick <= read_tick[-1])
    window = program & (rec["sp_new"] == 1)
    one_way = (rec["sp_rx_ns"][window].astype(np.int64)
               - rec["sp_t_ns"][window].astype(np.int64)) * 1e-9
    delay = float(np.median(one_way))
    jitter = float(one_way.max()) - delay
    lateness = npz["lateness_ns"]
    k = npz["k"][(npz["k"] >= 0) & (npz["k"] < lateness.size)]
    ctl_late = float(lateness[k].max()) * 1e-9 if k.size else 0.0
    emu_late = max(0.0, float(rec["lateness_ns"][program].max()) * 1e-9)
    m = max(1, math.ceil((delay + jitter + ctl_late + emu_late) / period_s))
    dt = float(np.median(np.diff(ls.column("t_s"))))
    v = np.diff(ls.si(ls.resolve("pos_set_mm"))) / dt
    v_max = float(np.abs(v).max()) if v.size else 0.0
    a_max = float(np.abs(np.diff(v)).max() / dt) if v.size > 1 else 0.0
    resolution = ctrl.scale_res or ctrl.rad_per_count * ctrl.ratio
    mt = m * period_s
    value = LOOP_PEAK * (v_max * mt + 0.5 * a_max * mt ** 2) + 2.0 * resolution
    return Tolerance(delay, jitter, ctl_late, emu_late, m, v_max, a_max, resolution, value)
