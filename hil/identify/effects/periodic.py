"""Effects periodic in a position: cogging (motor angle) and the screw's pitch error
(table position).

Both are sums of harmonics ``A sin(k phi + phase)`` and fit linearly as sine and cosine
columns once the orders (periods) are chosen; the orders come from the residual's
position-domain spectrum (seed 002).
"""

import math

import numpy as np

from hil.identify.conventions import apply_conventions, read_conventions
from hil.identify.effects.base import POSITION, Effect, Term, explained, lstsq
from hil.identify.effects.drivetrain import NO_SECOND_SENSOR
from hil.identify.spectrum import position_spectrum

MAX_HARMONICS = 4
#: lines of the residual's spectrum against the motor angle offered as cogging orders
SPECTRAL_LINES = 4
#: distance (orders per electrical revolution) within which a spectral line is a whole order
WHOLE_ORDER = 0.02


def _sincos(phase: np.ndarray, orders) -> np.ndarray:
    cols = []
    for k in orders:
        cols += [np.sin(k * phase), np.cos(k * phase)]
    return np.stack(cols, axis=1) if cols else np.zeros((phase.size, 0))


def _amp_phase(coef: np.ndarray, scale: float) -> tuple[list[float], list[float]]:
    """(s, c) pairs of s sin + c cos -> amplitudes and phases (deg) of
    scale * (s sin + c cos) = A sin(. + phase)."""
    amps, phases = [], []
    for s, c in coef.reshape(-1, 2):
        amps.append(float(abs(scale) * math.hypot(s, c)))
        phases.append(float(math.degrees(math.atan2(scale * c, scale * s))))
    return amps, phases


def _greedy_orders(cols_of, candidates, residual, mask, min_gain, start=0.0):
    """Pick orders one at a time while each removes at least ``min_gain`` of the residual
    energy more than the last (``start``: what ``cols_of([])`` explains); returns (orders,
    coef, explained)."""
    chosen: list[float] = []
    coef = np.zeros(0)
    ex = start
    for _ in range(MAX_HARMONICS):
        best = None
        for k in candidates:
            if k in chosen:
                continue
            cols = cols_of(chosen + [k])
            c = lstsq(cols, residual, mask)
            e = explained(residual, cols @ c, mask)
            if best is None or e > best[0]:
                best = (e, k, c)
        if best is None or best[0] - ex < min_gain:
            break
        ex, k, coef = best
        chosen.append(k)
    return chosen, coef, ex


class Cogging(Effect):
    """Cogging: a force residual periodic in the motor's electrical angle, at the whole
    orders 1 to MAX_ORDER per electrical revolution and at the orders of the strongest
    lines of the residual's spectrum against the angle (any order the low-pass keeps)."""
    name = "cogging"
    n_params = 2
    #: the closed loop weighs a fast periodic force's amplitude far more than the inverse
    #: model: on the second generator's 120 Hz cogging trace the fit's 0.44 % short
    #: amplitude replayed at 1.52x the current's floor and 1.49x the scale's, the
    #: refinement's (0.02 % off) at 1.29 / 0.87, the truth's own 1.28 / 0.86 (issue 30)
    refined_per_coefficient = True
    #: whole electrical orders always looked at
    MAX_ORDER = 12

    def declared(self, ctx):
        cg = ctx.cfg.cogging
        if not cg.orders:
            return None
        amps = cg.amplitudes_n if ctx.drive.kind == "linear" else cg.amplitudes_nm
        phases = cg.phases_deg or (0.0,) * len(cg.orders)
        coef = []
        for a, ph in zip(amps, phases):
            # torque A sin(k th + ph) at the motor is -A/r sin(...) in the force balance
            s = -a / ctx.drive.ratio
            coef += [s * math.cos(math.radians(ph)), s * math.sin(math.radians(ph))]
        return Term(self, {"orders": [float(k) for k in cg.orders]}, np.array(coef))

    def _resolvable(self, ctx, order):
        """Fraction of the moving samples where this order's time frequency stays below the
        low-pass corner (above it the filter has removed the line)."""
        m = ctx.m
        w_e = np.abs(np.gradient(m.theta_e, ctx.rec.dt))
        f = order * w_e / (2 * math.pi)
        return float(np.mean(f[ctx.moving] < 0.7 * m.cutoff_hz))

    def _spectral_orders(self, ctx, residual) -> list[float]:
        """Orders per electrical revolution of the strongest lines of the residual's
        spectrum against the motor's electrical angle (seed 002): any order, fractional
        ones too (a slot count that is no multiple of the pole pairs), up to the corner."""
        mask = ctx.moving
        cycles = ctx.m.theta_e / (2 * math.pi)
        span = float(np.ptp(cycles[mask])) if mask.any() else 0.0
        if span <= 2.0:
            return []
        # bins of 1/(16 MAX_ORDER) revolution: lines up to 4 MAX_ORDER (peaks() keeps half
        # the bins' Nyquist frequency)
        spec = position_spectrum(residual, cycles, mask, 1.0 / (16 * self.MAX_ORDER))
        # at least once per mechanical revolution (per pole pair on a linear motor): a
        # slower line is the load's, not the motor's
        lowest = 1.0 / ctx.drive.pole_pairs if ctx.drive.kind != "linear" else 1.0
        # a line within the bins' reach of a whole order is that order
        return [float(round(f)) if abs(f - round(f)) < WHOLE_ORDER else round(f, 3)
                for f, _ in spec.peaks(SPECTRAL_LINES, min_cycles=2.0 / span)
                if f >= lowest * 0.99]

    def propose(self, ctx, residual, model):
        found = self._spectral_orders(ctx, residual)
        orders = sorted({float(k) for k in range(1, self.MAX_ORDER + 1)} | set(found))
        orders = [k for k in orders if self._resolvable(ctx, k) > 0.5]
        if not orders:
            return None
        mask = ctx.moving
        chosen, coef, ex = _greedy_orders(lambda ks: self.columns(ctx, {"orders": ks}), orders,
                                          residual, mask, 0.01)
        if not chosen:
            return None
        amps, _ = _amp_phase(coef, 1.0)
        per_rev = ctx.drive.pole_pairs if ctx.drive.kind != "linear" else None
        ev = {"explained": ex, "orders_per_electrical_rev": chosen, "amplitudes": amps,
              "orders_per_mechanical_rev": [k * per_rev for k in chosen] if per_rev else None,
              "spectral_orders": found,
              "text": "residual periodic in the motor angle: " + ", ".join(
                  f"order {k:g} per electrical revolution, {a:.3g}" for k, a in
                  zip(chosen, amps))}
        return Term(self, {"orders": chosen}, coef, True, ev)

    def columns(self, ctx, shape):
        # the angle is raw (quantized but not delayed): filter its harmonics like the force
        cols = _sincos(ctx.m.theta_e, shape["orders"])
        return np.stack([ctx.m.lowpass(c) for c in cols.T], axis=1) if cols.size else cols

    def n_coef(self, shape):
        return 2 * len(shape["orders"])

    def params(self, ctx, shape, coef):
        amps, phases = _amp_phase(coef, -ctx.drive.ratio)
        unit = "amplitudes_n" if ctx.drive.kind == "linear" else "amplitudes_nm"
        return {"orders": list(shape["orders"]), unit: amps, "phases_deg": phases}

    def overrides(self, ctx, shape, coef, model):
        return {"cogging": self.params(ctx, shape, coef)}


#: harmonics of the lead tried as pitch-error periods (lead / k), besides the spectrum's
LEAD_HARMONICS = 4


class PitchError(Effect):
    """Pitch (lead) error of the screw: table position minus motor position, periodic in
    the table position -- harmonics of the lead (the screw's own run-out and thread
    errors: periods lead / k), and the long-wave periods the residual's spectrum shows --
    plus a cumulative lead error c x (``linear_ppm``) where it explains as much as a
    harmonic must, as the plant's e(u) = sum A_k sin(2 pi u / P_k + phi_k) + c u.

    Every fit of the proposal has a constant d beside them: the encoders' zeros differ
    (encoders zeroed at the start, away from x = 0, differ by -e(x_0); issue 30).  Without
    it a short travel's offset goes into a slope and beating periods.  d is no plant
    parameter, so the term leaves it out (the domain's joint fit has its own offset,
    :meth:`hil.identify.model.Model.refit`); the evidence says what it is."""
    name = "pitch_error"
    domain = POSITION
    n_params = 2

    def unavailable(self, ctx):
        if ctx.drive.kind != "screw":
            return "only a ball screw has a pitch error"
        if ctx.m.dx is None:
            return NO_SECOND_SENSOR
        return None

    def declared(self, ctx):
        pe = getattr(ctx.cfg, "pitch_error", None)
        if pe is None or not (pe.periods_m or pe.linear_ppm):
            return None
        phases = pe.phases_deg or (0.0,) * len(pe.periods_m)
        coef = []
        for a, ph in zip(pe.amplitudes_m, phases):
            coef += [a * math.cos(math.radians(ph)), a * math.sin(math.radians(ph))]
        linear = pe.linear_ppm != 0.0
        return Term(self, {"periods_m": list(pe.periods_m), "linear": linear},
                    np.array(coef + ([pe.linear_ppm * 1e-6] if linear else [])))

    def _cols(self, ctx, periods, linear=False, offset=False):
        """The harmonics' sine and cosine columns (and the cumulative error's, c x: the
        plant's e(u) = c u from the screw's zero; and the constant's, with ``offset``),
        shape (n, 2k (+ 1) (+ 1))."""
        x = ctx.m.x
        cols = [_sincos(2 * math.pi * x, [1.0 / p for p in periods])]
        if linear:
            cols.append(x[:, None])
        if offset:
            cols.append(np.ones((x.size, 1)))
        return np.hstack(cols)

    def propose(self, ctx, residual, model):
        mask = ctx.moving
        x = ctx.m.x[mask]
        travel = float(x.max() - x.min()) if x.size else 0.0
        if travel <= 0:
            return None
        # shortest period looked at: eight samples per period at the top speed
        vmax = float(np.max(np.abs(ctx.m.v[mask])))
        p_min = max(8 * vmax * ctx.rec.dt, travel / 2000)
        spec = position_spectrum(residual, ctx.m.x, mask, p_min / 4)
        # a period must fit about one and a half times into the travel to tell it from a slope
        peaks = spec.peaks(2 * MAX_HARMONICS, min_cycles=1.5 / travel)
        periods = [self._refine(ctx, residual, mask, f, spec.resolution)
                   for f, _ in peaks if 1.0 / f >= p_min]
        lead = 2 * math.pi * ctx.drive.ratio
        periods += [lead / k for k in range(1, LEAD_HARMONICS + 1) if lead / k >= p_min]
        alone = self._cols(ctx, [], offset=True)
        start = explained(residual, alone @ lstsq(alone, residual, mask), mask)
        chosen, coef, ex = _greedy_orders(lambda ps: self._cols(ctx, ps, offset=True),
                                          periods, residual, mask, 0.01, start)
        if not chosen:
            return None
        chosen, coef, ex = self._refine_jointly(ctx, residual, mask, chosen, lead,
                                                spec.resolution, (coef, ex))
        # the cumulative lead error, when it explains as much more as a harmonic must
        cols = self._cols(ctx, chosen, True, True)
        with_linear = lstsq(cols, residual, mask)
        ex_linear = explained(residual, cols @ with_linear, mask)
        linear = ex_linear - ex >= 0.01
        if linear:
            coef, ex = with_linear, ex_linear
        shape = {"periods_m": chosen, "linear": linear}
        coef, d = coef[:-1], float(coef[-1])
        amps, _ = _amp_phase(coef[:2 * len(chosen)], 1.0)
        ppm = float(coef[-1]) * 1e6 if linear else 0.0
        zero = self._zero_offset(ctx, shape, coef, d, residual, model)
        ev = {"explained": ex, "periods_m": chosen, "amplitudes_m": amps,
              "periods_per_lead": [p / lead for p in chosen], "linear_ppm": ppm, **zero,
              "text": "table position minus motor position is periodic in the table "
                      "position: " + ", ".join(f"period {p * 1e3:.4g} mm ({p / lead:.3g} "
                                               f"lead), {a * 1e6:.3g} um"
                                               for p, a in zip(chosen, amps))
                      + (f"; cumulative lead error {ppm:.3g} um/m" if linear else "")
                      + "; " + zero["offset_text"]}
        return Term(self, shape, coef, True, ev)

    def _zero_offset(self, ctx, shape, coef, d, residual, model) -> dict:
        """What the fitted constant says about the encoders' zeros: ``offset_m``, table
        minus motor position where the pitch error is 0 (the residual's centring undone),
        ``zero_at_start_m``, the offset encoders zeroed at the record's first position x_0
        show, -e(x_0) (so that both read 0 there), and ``offset_text``."""
        # the residual is centred: its mean over the used samples is added back
        raw = ctx.m.dx - model.prediction(POSITION)
        offset = d + float(np.mean((raw - residual)[ctx.m.use]))
        at_start = -float(self.columns(ctx, shape)[0] @ coef)
        cfg = apply_conventions(ctx.cfg, read_conventions(ctx.rec, ctx.cfg))
        zeroed = cfg.sensors.encoder_zero_at_start
        if zeroed:
            text = (f"the encoders' zeros differ by {offset * 1e6:.3g} um: encoders zeroed "
                    f"at the start (encoder_zero_at_start) differ by -e(x_0) = "
                    f"{at_start * 1e6:.3g} um, at x_0 = {ctx.m.x[0] * 1e3:.4g} mm")
        else:
            text = (f"the encoders' zeros differ by {offset * 1e6:.3g} um (no plant "
                    "parameter: left out of the machine file)")
        return {"offset_m": offset, "zero_at_start_m": at_start, "offset_text": text}

    def _refine_jointly(self, ctx, residual, mask, chosen, lead, resolution, fit):
        """``chosen`` with each spectral period (no lead harmonic) refined again beside the
        others: refined alone, another period's leakage pulls it off (by 0.3 % against a
        lead harmonic of a third its amplitude: 3.6x the floor over 60 mm); returns
        (periods, coef, explained), ``fit`` = (coef, explained) of ``chosen`` as given."""
        periods = list(chosen)
        for i, p in enumerate(chosen):
            if any(math.isclose(p, lead / k) for k in range(1, LEAD_HARMONICS + 1)):
                continue
            others = periods[:i] + periods[i + 1:]
            periods[i] = self._refine(ctx, residual, mask, 1.0 / p, resolution, others)
        cols = self._cols(ctx, periods, offset=True)
        coef = lstsq(cols, residual, mask)
        ex = explained(residual, cols @ coef, mask)
        return (periods, coef, ex) if ex > fit[1] else (chosen, *fit)

    def _refine(self, ctx, residual, mask, cycles, resolution, others=()):
        """The period within one spectral line of ``cycles`` (cycles/m) that explains
        most of the residual, fitted beside the periods ``others`` (m)."""
        from scipy.optimize import minimize_scalar

        def unexplained(f):
            cols = self._cols(ctx, [1.0 / f, *others], offset=True)
            return -explained(residual, cols @ lstsq(cols, residual, mask), mask)

        lo = max(cycles - resolution, 0.5 * cycles)
        sol = minimize_scalar(unexplained, bounds=(lo, cycles + resolution), method="bounded",
                              options={"xatol": 1e-4 * cycles})
        return float(1.0 / sol.x)

    def columns(self, ctx, shape):
        return self._cols(ctx, shape["periods_m"], shape.get("linear", False))

    def n_coef(self, shape):
        return 2 * len(shape["periods_m"]) + int(shape.get("linear", False))

    def params(self, ctx, shape, coef):
        k = 2 * len(shape["periods_m"])
        amps, phases = _amp_phase(coef[:k], 1.0)
        return {"periods_m": list(shape["periods_m"]), "amplitudes_m": amps,
                "phases_deg": phases,
                "linear_ppm": float(coef[k]) * 1e6 if shape.get("linear") else 0.0}

    def overrides(self, ctx, shape, coef, model):
        return {"pitch_error": self.params(ctx, shape, coef)}
