"""Which fault of the catalog (:mod:`hil.inject.catalog`) a record shows (issue 14 part 6).

After identification the record is read as a condition-monitoring engineer reads it
against the healthy machine file, and each fault is named with its evidence, an estimate
of its level in the catalog's unit and what else could explain the same evidence:

* **force side** (:func:`hil.identify.changes.declared_changes`): friction coefficients up
  beyond their tolerance with the inertia as declared is ``friction_growth``; the inertia
  up too, by about the same factor 1/(1 - loss), is ``torque_constant_loss`` (fewer
  newtons per ampere scale every force-side coefficient alike);
* **ripple** (:func:`ripple_evidence`): the final model's force residual regressed on
  ``sin/cos(k theta_e)`` (a load-independent ripple) and ``i_load sin/cos(k theta_e)``
  (one proportional to the current the model says the motion needs) at whole electrical
  orders: order 1 load-independent is a
  phase-current offset, order 2 proportional a phase-current gain error, another order
  proportional a torque ripple;
* **drive train** (:func:`train_evidence`): table minus motor position regressed on the
  transmitted force (compliance), the flank in contact (a gap) and the travel (a drift of
  the motor encoder), on the record and on the healthy machine's replay of it: what the
  declared mechanics or the inverse model get wrong is in both and cancels;
* **encoder noise** (:func:`encoder_noise_counts`): the motor encoder's sample-to-sample
  scatter against the healthy replay, in counts, far above its quantisation.

Thresholds are in units of each estimate's standard uncertainty (``Z_MIN``) and a
physical floor per fault, so a healthy record names none.
"""

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from hil.identify.changes import asked_pct, asked_text
from hil.identify.effects import FORCE
from hil.identify.effects.drivetrain import contact_side, transmitted_force
from hil.identify.motion import motion
from hil.inject.catalog import FAULTS

#: smallest estimate, in standard uncertainties, that names a fault
Z_MIN = 8.0
#: whole electrical orders the ripple regression looks at
RIPPLE_ORDERS = (1, 2, 3, 4, 5, 6)
#: smallest load-independent ripple named, as q current (A)
RIPPLE_MIN_A = 0.02
#: smallest current-proportional ripple named (share of the current, 1)
RIPPLE_MIN_SHARE = 0.01
#: largest ratio of the inertia's and Coulomb friction's factors still "one factor"
ONE_FACTOR = 1.25
#: motor-encoder scatter (counts rms) above which it is noise: quantisation gives 0.4, and
#: where the faulty motion parts from the healthy replay (a gap, a soft nut) up to about 8
NOISE_MIN_COUNTS = 10.0
#: smallest drift of the motor encoder against the scale named (1e-6 of the travel)
DRIFT_MIN_PPM = 30.0
#: smallest change of backlash named (m) and of the train's compliance (share of the nut's)
GAP_MIN_M = 2e-6
COMPLIANCE_MIN = 0.2
_FRICTION_KEYS = ("coulomb_n", "viscous_ns_per_m", "static_minus_coulomb")


@dataclass(frozen=True)
class Fault:
    """One named fault.

    Attributes:
        name: the catalog's name (:data:`hil.inject.catalog.FAULTS`).
        level: the estimated level, in ``unit``.
        level_key: the catalog's level key (``growth_pct``, ``offset_a``, ...).
        unit: the level's unit.
        score: the evidence over its threshold (>= 1); faults are listed by it.
        evidence: what points to it, one sentence with the numbers.
        alternatives: what else would show the same evidence.
        extra: further numbers (the ripple's order, ...).
    """
    name: str
    level: float
    level_key: str
    unit: str
    score: float
    evidence: str
    alternatives: str
    extra: dict

    def line(self) -> str:
        unit = "" if self.unit == "1" else f" {self.unit}"
        return f"{self.name}: {self.level_key} ~ {self.level:.3g}{unit} ({self.evidence})"


def _named(name: str, level: float, score: float, evidence: str, alternatives: str,
           extra: dict) -> Fault:
    """A :class:`Fault` of the catalog's ``name``, with its level key and unit."""
    f = FAULTS[name]
    return Fault(name, level, f.level_key, f.unit, score, evidence, alternatives, extra)


def _changes(ident) -> dict:
    return {row["parameter"]: row for row in ident.declared_changes}


def force_side(ident) -> list[Fault]:
    """``friction_growth`` or ``torque_constant_loss`` from the declared coefficients'
    changes the data ask for (each in per cent of the declared value; tolerance per
    effect): beyond the tolerance they are findings the model did not take."""
    rows = _changes(ident)
    mass = rows.get("mass_kg")
    grown = [rows[k] for k in _FRICTION_KEYS
             if k in rows and rows[k]["beyond_tolerance"] and asked_pct(rows[k]) > 0]
    if not grown:
        return []
    coulomb = rows.get("coulomb_n")
    lead = coulomb if coulomb in grown else grown[0]
    listed = ", ".join(f"{r['parameter']} {asked_text(r)}" for r in grown)
    f_fric = 1.0 + asked_pct(lead) / 100.0
    score = abs(asked_pct(lead)) / lead["tolerance_pct"]
    if mass is not None and mass["beyond_tolerance"] and asked_pct(mass) > 0:
        f_mass = 1.0 + asked_pct(mass) / 100.0
        if max(f_mass / f_fric, f_fric / f_mass) <= ONE_FACTOR:
            return [_named(
                "torque_constant_loss", 100.0 * (1.0 - 1.0 / f_mass),
                min(score, asked_pct(mass) / mass["tolerance_pct"]),
                f"inertia {asked_text(mass)} and friction ({listed}) up by about "
                "one factor 1/(1 - loss): the torque per ampere dropped",
                "a gain error of the current measurement that reads high on every phase "
                "(ours, on phase a only, would also ripple at 2x the electrical frequency)",
                {"inertia_change_pct": asked_pct(mass)})]
    return [_named(
        "friction_growth", asked_pct(lead), score,
        f"friction beyond its tolerance ({listed}), inertia "
        + (asked_text(mass) if mass else "as declared"),
        "a changed load or lubrication state; viscous friction lumps in the motor's and "
        "bearings' drag, which the growth leaves alone, so it grows less", {})]


@dataclass(frozen=True)
class Ripple:
    """One electrical order's ripple in the force residual.

    Attributes:
        order: per electrical revolution.
        const_a, const_sigma_a: load-independent amplitude as q current (A), its uncertainty.
        share, share_sigma: current-proportional amplitude as a share of iq (1), its
            uncertainty.
        load_rms_a: rms of the load current it is a share of (A).
    """
    order: int
    const_a: float
    const_sigma_a: float
    share: float
    share_sigma: float
    load_rms_a: float


def _amp(coef: np.ndarray, cov: np.ndarray, j: int) -> tuple[float, float]:
    """Amplitude of the (sin, cos) pair at columns j, j+1 and its standard uncertainty."""
    s, c = coef[j], coef[j + 1]
    a = math.hypot(s, c)
    g = np.array([s, c]) / a if a > 0 else np.array([1.0, 1.0]) / math.sqrt(2.0)
    return float(a), float(math.sqrt(max(g @ cov[j:j + 2, j:j + 2] @ g, 0.0)))


def ripple_evidence(ident) -> list[Ripple]:
    """Ripples at :data:`RIPPLE_ORDERS` in the final model's force residual (N), fitted
    jointly with nuisance columns (acceleration, velocity, sign of velocity, a constant:
    what is left of the rigid-body terms); the columns see the force's low-pass.
    Uncertainties from the fit, widened for the low-pass's correlated samples."""
    m, ctx, rec = ident.motion, ident.ctx, ident.rec
    mask = ctx.moving
    residual = ident.model.residual(FORCE)
    # the load a ripple grows with: the current the model says the motion needs (A),
    # free of the measurement's noise and of the loop's answer to the ripple itself
    # (the measured current, which carries both, overstates a 5 % ripple by a fifth)
    load = (m.force - residual) / ident.drive.force_per_amp
    cols = [m.a, m.v, np.sign(m.v), np.ones(rec.n)]
    for k in RIPPLE_ORDERS:
        s, c = np.sin(k * m.theta_e), np.cos(k * m.theta_e)
        cols += [m.lowpass(s), m.lowpass(c), m.lowpass(load * s), m.lowpass(load * c)]
    a = np.stack(cols, axis=1)[mask]
    y = residual[mask]
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[scale == 0.0] = 1.0
    an = a / scale
    coef, *_ = np.linalg.lstsq(an, y, rcond=None)
    dof = max(y.size - a.shape[1], 1)
    s2 = float(np.sum((y - an @ coef) ** 2)) / dof
    # the low-pass leaves n_eff independent samples of n
    s2 *= y.size / max(min(ident.n_eff, y.size), 1.0)
    cov = s2 * np.linalg.pinv(an.T @ an) / np.outer(scale, scale)
    coef = coef / scale
    kf = ident.drive.force_per_amp
    load_rms = float(np.sqrt(np.mean(load[mask] ** 2)))
    out = []
    for i, k in enumerate(RIPPLE_ORDERS):
        j = 4 + 4 * i
        ca, cs = _amp(coef, cov, j)
        pa, ps = _amp(coef, cov, j + 2)
        out.append(Ripple(k, ca / kf, cs / kf, pa / kf, ps / kf, load_rms))
    return out


def ripple_faults(ripples: list[Ripple]) -> list[Fault]:
    """The current-sensor faults and the torque ripple their ripples point to.  The
    residual is the force the model lacks, so a true q-current ripple of amplitude r
    shows as r here: an offset o gives 2 o / sqrt(3) at order 1, a gain error g gives
    g iq / sqrt(3) at order 2, a torque ripple a gives a iq at its order."""
    out = []
    for r in ripples:
        z_const = r.const_a / r.const_sigma_a if r.const_sigma_a > 0 else 0.0
        z_share = r.share / r.share_sigma if r.share_sigma > 0 else 0.0
        const_ok = z_const >= Z_MIN and r.const_a >= RIPPLE_MIN_A
        # a proportional part much smaller than the load-independent ripple of its order
        # is that ripple's modulation by the loop, not a second fault
        share_ok = (z_share >= Z_MIN and r.share >= RIPPLE_MIN_SHARE
                    and not (const_ok and r.share * r.load_rms_a < r.const_a))
        score_c = min(z_const / Z_MIN, r.const_a / RIPPLE_MIN_A)
        score_s = min(z_share / Z_MIN, r.share / RIPPLE_MIN_SHARE)
        extra = {"order": r.order, "load_independent_a": r.const_a,
                 "load_independent_sigma_a": r.const_sigma_a, "share_of_iq": r.share,
                 "share_sigma": r.share_sigma}
        if r.order == 1 and const_ok:
            out.append(_named(
                "current_offset", r.const_a * math.sqrt(3.0) / 2.0, score_c,
                f"a load-independent ripple at 1x the electrical frequency, "
                f"{r.const_a:.3g} ± {r.const_sigma_a:.2g} A of q current",
                "a phase-current offset on any one sensor (the sign and phase are not "
                "estimated), or an order-1 cogging (rotor eccentricity)", extra))
        if share_ok and r.order == 2:
            out.append(_named(
                "current_gain_error", 100.0 * r.share * math.sqrt(3.0), score_s,
                f"a ripple at 2x the electrical frequency proportional to the current, "
                f"{100 * r.share:.3g} ± {100 * r.share_sigma:.2g} % of iq",
                "a torque ripple of order 2 (a broken-bar-like fault), which also grows "
                "with the load; a gain error also lowers the mean torque by about half "
                "of it", extra))
        elif share_ok:
            out.append(_named(
                "torque_ripple", 100.0 * r.share, score_s,
                f"a ripple at order {r.order} of the electrical frequency proportional to "
                f"the current, {100 * r.share:.3g} ± {100 * r.share_sigma:.2g} % of iq",
                "a current-sensor gain error if the order were 2; cogging does not grow "
                "with the load", extra))
    return out


@dataclass(frozen=True)
class Train:
    """Table minus motor position (m) regressed on the transmitted force (N), the flank
    in contact and the travel from the start (m), shape of each fit's coefficients (4,):
    compliance (m/N), half the gap (m), drift (1), offset (m)."""
    measured: np.ndarray
    healthy: np.ndarray
    sigma: np.ndarray


def _train_fit(ident, m) -> tuple[np.ndarray, np.ndarray]:
    ctx = replace(ident.ctx, m=m)
    force = transmitted_force(ctx)
    band = 0.1 * float(np.std(force[m.use]))
    cols = np.stack([force, contact_side(force, band), m.x - m.x[m.use][0],
                     np.ones(m.x.size)], axis=1)[m.use]
    y = m.dx[m.use]
    coef, *_ = np.linalg.lstsq(cols, y, rcond=None)
    s2 = float(np.sum((y - cols @ coef) ** 2)) / max(y.size - 4, 1)
    s2 *= y.size / max(min(ident.n_eff, y.size), 1.0)
    return coef, np.sqrt(np.diag(s2 * np.linalg.pinv(cols.T @ cols)))


def train_evidence(ident) -> Train | None:
    """The drive-train fit on the record and on the healthy machine file's replay of it
    (None without a motor encoder beside the scale, or when the replay failed)."""
    rep = ident.replay_before
    if ident.motion.dx is None or rep is None or rep.status != 0 or rep.motor_pos is None:
        return None
    healthy = replace(ident.rec, pos=rep.pos, motor_pos=rep.motor_pos, effort=rep.effort)
    m_h = motion(healthy, ident.drive, ident.motion.cutoff_hz)
    measured, sigma = _train_fit(ident, ident.motion)
    reference, sigma_h = _train_fit(ident, m_h)
    return Train(measured, reference, np.hypot(sigma, sigma_h))


def train_faults(ident, train: Train) -> list[Fault]:
    """``backlash_growth``, ``preload_loss`` and ``encoder_lost_counts`` from the change
    of the drive-train fit against the healthy replay's."""
    d = train.measured - train.healthy
    z = np.abs(d) / np.where(train.sigma > 0, train.sigma, np.inf)
    out = []
    extra = {"measured": train.measured.tolist(), "healthy": train.healthy.tolist(),
             "sigma": train.sigma.tolist()}
    gap = 2.0 * abs(d[1])
    fitted = ident.model.term("backlash")
    if fitted is not None:
        # the library's backlash, fitted on the flank changes themselves, measures the gap
        # better than this regression's step: its growth over the declared gap, if any
        declared = ident.model.declared.get("backlash")
        grown = float(fitted.coef[0]) - (float(declared[0]) if declared is not None else 0.0)
        if grown >= GAP_MIN_M:
            gap = grown
            z[1] = max(z[1], Z_MIN * gap / GAP_MIN_M)
    if z[1] >= Z_MIN and gap >= GAP_MIN_M:
        out.append(_named(
            "backlash_growth", gap, min(z[1] / Z_MIN, gap / GAP_MIN_M),
            f"table minus motor position jumps by {gap * 1e6:.3g} µm more than the healthy "
            "machine's when the force changes flank",
            "a loose coupling or a worn thrust bearing (any gap in the train)", extra))
    cfg = ident.ctx.cfg
    k_nut = cfg.screw.nut_stiffness_n_per_m if cfg.mechanics.model == "screw" else 0.0
    # the table lags the motor under a forward force: a softer train makes the
    # (negative) slope steeper
    softer = -d[0]
    if k_nut > 0 and z[0] >= Z_MIN and softer * k_nut >= COMPLIANCE_MIN:
        loss = 1.0 - 1.0 / (1.0 + softer * k_nut)
        out.append(_named(
            "preload_loss", 100.0 * loss,
            min(z[0] / Z_MIN, softer * k_nut / COMPLIANCE_MIN),
            f"the train is {softer * 1e9:.3g} nm/N softer than the healthy machine's "
            f"(the nut declares {1e9 / k_nut:.3g} nm/N)",
            "a softer screw, thrust bearing or mounting (the level assumes it is the nut)",
            extra))
    ppm = d[2] * 1e6
    if z[2] >= Z_MIN and abs(ppm) >= DRIFT_MIN_PPM:
        out.append(_named(
            "encoder_lost_counts", abs(ppm),
            min(z[2] / Z_MIN, abs(ppm) / DRIFT_MIN_PPM),
            f"the motor encoder drifts against the scale by {ppm:+.3g} µm per metre of "
            "travel", "a lead error of the screw or a scale error (a drift proportional to "
            "the travel looks the same; lost counts are a random walk around it)", extra))
    return out


def encoder_noise_counts(ident) -> float | None:
    """rms of the motor encoder's sample-to-sample scatter against the healthy replay, in
    counts, with the two readings' quantisation (1/12 count² each) taken out; None
    without a motor encoder or a replay."""
    rec, rep, cfg = ident.rec, ident.replay_before, ident.ctx.cfg
    if (rec.motor_pos is None or rep is None or rep.status != 0 or rep.motor_pos is None
            or cfg.machine.kind == "linear"):
        return None
    count_m = ident.drive.ratio * 2.0 * math.pi / cfg.sensors.encoder_counts_per_rev
    e = (rec.motor_pos - rep.motor_pos) / count_m
    # fourth differences of white noise have 70 times its variance and take the smooth
    # part of the motion's difference out; the median absolute deviation ignores the
    # few samples where the motions part (a reversal, a stick-slip)
    d4 = np.diff(e[ident.motion.use], 4)
    sigma = 1.4826 * float(np.median(np.abs(d4 - np.median(d4)))) / math.sqrt(70.0)
    return math.sqrt(max(sigma * sigma - 1.0 / 6.0, 0.0))


def noise_faults(ident) -> list[Fault]:
    """``encoder_noise`` when the motor encoder's scatter exceeds NOISE_MIN_COUNTS."""
    sigma = encoder_noise_counts(ident)
    if sigma is None or sigma < NOISE_MIN_COUNTS:
        return []
    return [_named("encoder_noise", sigma, sigma / NOISE_MIN_COUNTS,
                  f"the motor encoder scatters by {sigma:.3g} counts rms from sample to "
                  "sample, its quantisation alone about 0.4",
                  "interference on the encoder cable, a dirty disc, a loose read head", {})]


def diagnose(ident) -> list[Fault]:
    """Every fault the identified record shows, strongest evidence first (empty: none).
    ``ident`` is a fitted :class:`hil.identify.fit.Identification`."""
    faults = force_side(ident) + ripple_faults(ripple_evidence(ident)) + noise_faults(ident)
    train = train_evidence(ident)
    if train is not None:
        faults += train_faults(ident, train)
    return sorted(faults, key=lambda f: -f.score)


def as_json(faults: list[Fault]) -> list[dict]:
    """The faults as report.json's ``faults`` list."""
    return [asdict(f) for f in faults]


def no_fault(effects_added: list[str]) -> str:
    """What a diagnosis that named no fault says, after identification added
    ``effects_added`` to the model: those effects are what the record showed, so "no
    fault" alone would read as "nothing found"."""
    if not effects_added:
        return "no fault found"
    return ("no fault of the catalog found beyond the effects added to the model ("
            + ", ".join(effects_added) + ")")


def faults_markdown(faults: list[dict], effects_added: list[str]) -> list[str]:
    """report.md's "Faults" section from report.json's ``faults`` and ``effects_added``."""
    lines = ["## Faults", ""]
    if not faults:
        text = no_fault(effects_added)
        return lines + [text[0].upper() + text[1:] + ".", ""]
    lines += ["| fault | level | evidence | could also be |", "|---|---|---|---|"]
    for f in faults:
        lines.append(f"| `{f['name']}` | {f['level_key']} ≈ {f['level']:.3g} {f['unit']} | "
                     f"{f['evidence']} | {f['alternatives']} |")
    return lines + [""]


def summary_lines(faults: list[dict], effects_added: list[str]) -> list[str]:
    """One line per fault for the command's output (:func:`no_fault` when none)."""
    if not faults:
        return [no_fault(effects_added)]
    return [f"fault: {f['name']} {f['level_key']} ~ {f['level']:.3g} {f['unit']}"
            for f in faults]
