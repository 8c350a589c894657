"""The measurement noise floor of each replay channel, and the acceptance of a step by it.

A closed-loop replay is noise-free; the record is not.  What no model can explain is the
measurement's own noise, per channel (the keys of :func:`hil.identify.replay.errors`):

* the effort (``iq_rms_a`` / ``force_rms_n``): its white noise, estimated robustly from
  the second difference of the record (for white noise of deviation s the second
  difference has deviation sqrt(6) s; a smooth servo signal sampled at 1 kHz adds little,
  and the median absolute deviation ignores the steps), and the ADC's step over sqrt(12)
  where the record is on a grid;
* each position (``pos_rms_um``/``pos_rms_urad``, ``motor_pos_rms_um``): the sensor's step
  over sqrt(12).  The step is the one the machine file or the record's header declares
  (``encoder_counts_per_rev`` through the lead, ``encoder_resolution_m``,
  ``scale_resolution_m``) where the record's changes are whole multiples of it; else the
  step fitted to the record's changes (:func:`~hil.identify.effects.base.quantum`, which
  tolerates the round-off of printed values); off any grid, the MAD estimate.
  :func:`floor_origins` says per channel which it was.

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

from hil.identify.conventions import apply_conventions, read_conventions
from hil.identify.effects.base import on_grid, quantum
from hil.identify.record import Record
from hil.identify.replay import Replay
from plant.assemble import transmission_ratio
from plant.config import MachineConfig

#: 1.4826 MAD is the standard deviation of Gaussian data
MAD_TO_SIGMA = 1.4826


def white_noise(x: np.ndarray) -> float:
    """Robust deviation of the white noise on ``x`` (n,) from its second difference."""
    if x.size < 5:
        return 0.0
    d2 = np.diff(x, 2)
    return float(MAD_TO_SIGMA * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _declared_steps(rec: Record, cfg: MachineConfig) -> dict:
    """The position sensors' steps ``cfg`` (with ``rec``'s header keys applied) declares,
    in table units (m or rad): {"pos": ..., "motor_pos": ...} as (step, sensor, the key
    that declares it), a sensor without a declared step left out."""
    conv = read_conventions(rec, cfg)
    cfg = apply_conventions(cfg, conv)
    sen = cfg.sensors

    def where(key: str) -> str:
        return f"{key} of the {'header' if key in conv.given else 'machine file'}"

    if cfg.machine.kind == "linear":
        motor = (sen.encoder_resolution_m, "motor encoder", where("encoder_resolution_m"))
    else:
        motor = (2.0 * math.pi * transmission_ratio(cfg) / sen.encoder_counts_per_rev,
                 "motor encoder", where("encoder_counts_per_rev")
                 + (" through the lead" if cfg.machine.kind == "screw" else ""))
    scale = None
    if cfg.machine.kind != "rotary" and sen.scale_resolution_m > 0.0:
        scale = (sen.scale_resolution_m, "scale", where("scale_resolution_m"))
    two_sensors = rec.motor_pos is not None and not np.array_equal(rec.motor_pos, rec.pos)
    # one position column is what the position loop read: the scale where it closes it
    by_scale = two_sensors or cfg.section("controller").get("feedback") == "scale"
    out = {"motor_pos": motor}
    pos = scale if by_scale else motor
    if pos is not None:
        out["pos"] = pos
    return out


def _length(q: float, rotary: bool) -> str:
    return f"{q * 1e6:.4g} µrad" if rotary else f"{q * 1e9:.4g} nm"


def _sensor(x: np.ndarray, declared: tuple | None, rotary: bool) -> tuple[float, str]:
    """rms quantisation (or white) noise of a position signal, same unit as ``x``, and how
    it was found."""
    if declared is not None:
        q, sensor, key = declared
        if on_grid(x, q):
            return q / math.sqrt(12.0), (f"the declared {sensor} step "
                                         f"{_length(q, rotary)} / sqrt(12), {key}")
    q = quantum(x)
    off = (f"; the declared {declared[1]} step {_length(declared[0], rotary)} does not fit "
           "the record's changes" if declared is not None else "")
    if q > 0:
        return q / math.sqrt(12.0), (f"grid fit: the record's step {_length(q, rotary)} / "
                                     f"sqrt(12){off}")
    return white_noise(x), f"white noise of the record's second difference (no grid){off}"


def _floors(rec: Record, cfg: MachineConfig | None) -> dict:
    """{channel: (floor, how it was found)} (module docstring)."""
    effort = "iq_rms_a" if rec.effort_kind == "iq" else "force_rms_n"
    lsb = quantum(rec.effort)
    noise = white_noise(rec.effort)
    # the MAD of a signal on a grid already holds part of its rounding: add what is missing
    if noise < lsb:
        out = {effort: (math.hypot(noise, lsb / math.sqrt(12.0)),
                        f"white noise of the record's second difference with the grid "
                        f"fit's step {lsb:.4g} / sqrt(12)")}
    else:
        out = {effort: (noise, "white noise of the record's second difference")}
    declared = _declared_steps(rec, cfg) if cfg is not None else {}
    pos = "pos_rms_urad" if rec.rotary else "pos_rms_um"
    value, how = _sensor(rec.pos, declared.get("pos"), rec.rotary)
    out[pos] = (value * 1e6, how)
    if rec.motor_pos is not None and not np.array_equal(rec.motor_pos, rec.pos):
        value, how = _sensor(rec.motor_pos, declared.get("motor_pos"), rec.rotary)
        out["motor_pos_rms_um"] = (value * 1e6, how)
    return out


def replay_floor(rec: Record, cfg: MachineConfig | None = None) -> dict:
    """The noise floor of every replay error channel of ``rec``, in the units of
    :func:`hil.identify.replay.errors` (µm, µrad, A, N); the positions' steps as ``cfg``
    (the machine file) or the record's header declare them, where they do."""
    return {k: v for k, (v, _) in _floors(rec, cfg).items()}


def floor_origins(rec: Record, cfg: MachineConfig | None = None) -> dict:
    """How :func:`replay_floor` found each channel's floor, in words."""
    return {k: how for k, (_, how) in _floors(rec, cfg).items()}


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
