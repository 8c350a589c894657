"""The measurement noise floor of each replay channel, and the acceptance of a step by it.

A closed-loop replay is noise-free; the record is not.  What no model can explain is the
measurement's own noise, per channel (the keys of :func:`hil.identify.replay.errors`):

* the effort (``iq_rms_a`` / ``force_rms_n``): its white noise, estimated robustly from
  the second difference of the record (for white noise of deviation s the second
  difference has deviation sqrt(6) s; a smooth servo signal sampled at 1 kHz adds little,
  and the median absolute deviation ignores the steps), and the ADC's step over sqrt(12)
  where the record is on a grid;
* each position (``pos_rms_um``/``pos_rms_urad``, ``motor_pos_rms_um``): the sensor's step
  over sqrt(12), the step being the record's quantum (or the MAD estimate off a grid).

A step of the search is judged by the normalised cost J = sum over channels of
(error / floor)^2: a channel at its floor weighs about 1 whatever its units, so a channel
getting a little worse at its floor cannot veto a real gain elsewhere (the old rule, "any
channel 10 % worse", did).  A step is kept when it lowers the Bayesian information
criterion n ln J + k ln n, n the effective number of independent samples (the record's
bandwidth after the inverse model's filter: 2 f_c per second) and k the parameters added.
"""

import math
from dataclasses import dataclass

import numpy as np

from hil.identify.effects.base import quantum
from hil.identify.record import Record
from hil.identify.replay import Replay

#: 1.4826 MAD is the standard deviation of Gaussian data
MAD_TO_SIGMA = 1.4826


def white_noise(x: np.ndarray) -> float:
    """Robust deviation of the white noise on ``x`` (n,) from its second difference."""
    if x.size < 5:
        return 0.0
    d2 = np.diff(x, 2)
    return float(MAD_TO_SIGMA * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _sensor(x: np.ndarray) -> float:
    """rms quantisation (or white) noise of a position signal, same unit as ``x``."""
    q = quantum(x)
    return q / math.sqrt(12.0) if q > 0 else white_noise(x)


def replay_floor(rec: Record) -> dict:
    """The noise floor of every replay error channel of ``rec``, in the units of
    :func:`hil.identify.replay.errors` (µm, µrad, A, N)."""
    effort = "iq_rms_a" if rec.effort_kind == "iq" else "force_rms_n"
    lsb = quantum(rec.effort)
    noise = white_noise(rec.effort)
    # the MAD of a signal on a grid already holds part of its rounding: add what is missing
    out = {effort: math.hypot(noise, lsb / math.sqrt(12.0)) if noise < lsb else noise}
    pos = "pos_rms_urad" if rec.rotary else "pos_rms_um"
    out[pos] = _sensor(rec.pos) * 1e6
    if rec.motor_pos is not None and not np.array_equal(rec.motor_pos, rec.pos):
        out["motor_pos_rms_um"] = _sensor(rec.motor_pos) * 1e6
    return out


@dataclass(frozen=True)
class Judgement:
    """A step's verdict: ``keep``, the normalised costs before and after, the criterion's
    change (negative: better) and the reason in words."""
    keep: bool
    cost_before: float
    cost_after: float
    delta_bic: float
    reason: str


def normalised_cost(err: dict, floor: dict) -> float:
    """J = sum over the floor's channels of (error / floor)^2 (inf when a channel is
    missing: a failed replay)."""
    total = 0.0
    for key, f in floor.items():
        value = err.get(key)
        if not isinstance(value, float) or f <= 0.0:
            return math.inf
        total += (value / f) ** 2
    return total


def judge(before: dict, after: dict, floor: dict, added_params: int, n_eff: float) -> Judgement:
    """Whether a step that adds ``added_params`` parameters and turns the replay's errors
    from ``before`` into ``after`` is worth keeping (module docstring)."""
    if "status" in after:
        return Judgement(False, normalised_cost(before, floor), math.inf, math.inf,
                         f"the replay failed ({after['status']})")
    j0, j1 = normalised_cost(before, floor), normalised_cost(after, floor)
    n = max(n_eff, 2.0)
    delta = n * math.log(j1 / j0) + added_params * math.log(n) if j0 > 0 else math.inf
    ratio = ", ".join(f"{k} {after[k] / f:.3g}x" for k, f in floor.items()
                      if isinstance(after.get(k), float) and f > 0)
    if delta < 0.0:
        return Judgement(True, j0, j1, delta, f"BIC {delta:+.1f} (J {j0:.4g} -> {j1:.4g}; "
                                              f"error/floor {ratio})")
    return Judgement(False, j0, j1, delta, f"the replay did not gain enough for "
                                           f"{added_params} parameter(s): BIC {delta:+.1f} "
                                           f"(J {j0:.4g} -> {j1:.4g}; error/floor {ratio})")


def channel_residuals(rec: Record, rep: Replay, floor: dict) -> list[np.ndarray]:
    """(record - replay) / floor for each channel of ``floor``, in its order (the unit of
    :func:`replay_floor`: µm, µrad, A, N), each shape (n,)."""
    out = []
    for key, f in floor.items():
        if key == "motor_pos_rms_um":
            y, y_hat, scale = rec.motor_pos, rep.motor_pos, 1e6
        elif key.startswith("pos_"):
            y, y_hat, scale = rec.pos, rep.pos, 1e6
        else:
            y, y_hat, scale = rec.effort, rep.effort, 1.0
        out.append((y - y_hat) * scale / f)
    return out
