"""Effects the inverse model's force residual shows: inertia, friction, a constant force.

Force balance at the table, in the measured motion (SI; N·m and rad on rotary tables)::

    F = M a + Fv v + dFv |v| + Fc sign(v) + (Fs - Fc) exp(-(v/vs)^2) sign(v) - F_ext
        - cog(theta_e)/r

Sign conventions follow the plant: friction opposes the motion, ``F_ext`` is the
external force pushing toward +x (``[table] external_force_n``).
"""

import numpy as np

from hil.identify.effects.base import Context, Effect, Term, correlation, explained, lstsq


def _linear_term(effect: Effect, ctx: Context, residual: np.ndarray,
                 evidence: dict) -> Term | None:
    cols = effect.columns(ctx, {})
    lo, hi = effect.bounds({})
    mask = effect.mask(ctx)
    coef = lstsq(cols, residual, mask, lo, hi)
    evidence["explained"] = explained(residual, cols @ coef, mask)
    return Term(effect, {}, coef, True, evidence)


def _rotary(ctx: Context) -> bool:
    return ctx.drive.kind == "rotary"


class Inertia(Effect):
    """Moved mass (inertia) differs from the config's: residual proportional to a."""
    name = "inertia"
    correctable = True

    def declared(self, ctx):
        return Term(self, {}, np.array([ctx.drive.mass]))

    def propose(self, ctx, residual, model):
        ev = {"corr_with_a": correlation(residual[ctx.moving], ctx.m.a[ctx.moving])}
        term = _linear_term(self, ctx, residual, ev)
        base = model.term(self.name)
        term.coef = term.coef + (base.coef if base is not None else 0.0)
        what, unit = ("inertia", "kg m²") if _rotary(ctx) else ("mass", "kg")
        change = term.coef[0] - ctx.drive.mass
        # the fit only adds (bounds from 0): no change is a clipped fit, said as such
        moved = (f"moved {what} unchanged at {ctx.drive.mass:.4g} {unit} (the residual asks "
                 "for no more)" if change == 0 else
                 f"moved {what} off by {change:+.4g} {unit} "
                 f"({100.0 * change / ctx.drive.mass:+.3g} % of {ctx.drive.mass:.4g})")
        ev["text"] = (f"residual correlates with acceleration (r = {ev['corr_with_a']:.2f}): "
                      + moved)
        return term

    def columns(self, ctx, shape):
        return ctx.m.a[:, None]

    def bounds(self, shape):
        return np.zeros(1), np.full(1, np.inf)

    def params(self, ctx, shape, coef):
        return {"inertia_kgm2" if _rotary(ctx) else "mass_kg": float(coef[0])}

    def overrides(self, ctx, shape, coef, model):
        cfg = ctx.cfg
        if _rotary(ctx):
            other = ctx.drive.mass - cfg.mechanics.load_inertia_kgm2
            return {"mechanics": {"load_inertia_kgm2": max(0.0, float(coef[0]) - other)}}
        other = ctx.drive.mass - cfg.table.mass_kg
        return {"table": {"mass_kg": max(0.0, float(coef[0]) - other)}}


class ViscousFriction(Effect):
    """Viscous friction: residual proportional to v."""
    name = "viscous_friction"
    correctable = True

    def declared(self, ctx):
        return Term(self, {}, np.array([ctx.drive.viscous])) if ctx.drive.viscous > 0 else None

    def propose(self, ctx, residual, model):
        ev = {"corr_with_v": correlation(residual[ctx.moving], ctx.m.v[ctx.moving])}
        term = _linear_term(self, ctx, residual, ev)
        base = model.term(self.name)
        if base is not None:
            term.coef = term.coef + base.coef
        ev["text"] = f"residual correlates with velocity (r = {ev['corr_with_v']:.2f})"
        return term

    def columns(self, ctx, shape):
        return ctx.m.v[:, None]

    def bounds(self, shape):
        return np.zeros(1), np.full(1, np.inf)

    def params(self, ctx, shape, coef):
        return {"viscous_nms_per_rad" if _rotary(ctx) else "viscous_ns_per_m": float(coef[0])}

    def overrides(self, ctx, shape, coef, model):
        key = "viscous_nms_per_rad" if _rotary(ctx) else "viscous_ns_per_m"
        return {"friction": {key: max(0.0, float(coef[0]) - ctx.drive.motor_viscous)}}


class ViscousAsymmetry(Effect):
    """Viscous friction that differs by direction (seals, preload, a lubricant film that
    builds differently): residual proportional to |v|, B + dB moving +, B - dB moving -."""
    name = "viscous_asymmetry"

    def _key(self, ctx):
        return ("viscous_asymmetry_nms_per_rad" if _rotary(ctx)
                else "viscous_asymmetry_ns_per_m")

    def declared(self, ctx):
        db = getattr(ctx.cfg.friction, self._key(ctx))
        return Term(self, {}, np.array([db])) if db != 0.0 else None

    def propose(self, ctx, residual, model):
        mov = ctx.moving
        ev = {"corr_with_abs_v": correlation(residual[mov], np.abs(ctx.m.v[mov]))}
        term = _linear_term(self, ctx, residual, ev)
        visc = model.term("viscous_friction")
        b = float(visc.coef[0]) if visc is not None else 0.0
        db = float(term.coef[0])
        # on a record with few speeds |v| and a constant look alike: say what it amounts to
        ev["mean_residual"] = float(residual[mov].mean())
        ev["as_constant"] = float(db * np.abs(ctx.m.v[mov]).mean())
        ev["text"] = (f"residual grows with |v| (r = {ev['corr_with_abs_v']:.2f}): viscous "
                      f"{b + db:.4g} moving +, {b - db:.4g} moving -; it carries "
                      f"{ev['as_constant']:+.3g} of the residual's mean "
                      f"{ev['mean_residual']:+.3g}")
        return term

    def columns(self, ctx, shape):
        return np.abs(ctx.m.v)[:, None]

    def params(self, ctx, shape, coef):
        return {self._key(ctx): float(coef[0])}

    def overrides(self, ctx, shape, coef, model):
        return {"friction": {self._key(ctx): float(coef[0])}}


def _coulomb_key(ctx):
    return "coulomb_nm" if _rotary(ctx) else "coulomb_n"


class CoulombFriction(Effect):
    """Coulomb friction: a step of the residual with the sign of v."""
    name = "coulomb_friction"
    correctable = True

    def declared(self, ctx):
        fc = getattr(ctx.cfg.friction, _coulomb_key(ctx))
        return Term(self, {}, np.array([fc])) if fc > 0 else None

    def propose(self, ctx, residual, model):
        s = np.sign(ctx.m.v)
        ev = {"corr_with_sign_v": correlation(residual[ctx.moving], s[ctx.moving])}
        term = _linear_term(self, ctx, residual, ev)
        base = model.term(self.name)
        if base is not None:
            term.coef = term.coef + base.coef
        ev["text"] = (f"residual steps with the direction of motion (correlation with "
                      f"sign(v) {ev['corr_with_sign_v']:.2f})")
        return term

    def columns(self, ctx, shape):
        return np.sign(ctx.m.v)[:, None]

    def bounds(self, shape):
        return np.zeros(1), np.full(1, np.inf)

    def params(self, ctx, shape, coef):
        return {_coulomb_key(ctx): float(coef[0])}

    def overrides(self, ctx, shape, coef, model):
        key = _coulomb_key(ctx)
        out = {key: float(coef[0])}
        # a breakaway level the file declares keeps its ratio to Coulomb's (F_H >= F_C);
        # a fitted Stribeck term writes its own
        k_fh = "breakaway_nm" if _rotary(ctx) else "breakaway_n"
        f_h, f_c = getattr(ctx.cfg.friction, k_fh), getattr(ctx.cfg.friction, key)
        if f_h > 0.0:
            out[k_fh] = f_h * float(coef[0]) / f_c if f_c > 0.0 else max(f_h, float(coef[0]))
        return {"friction": out}


class GravityOffset(Effect):
    """A constant force on the table (weight of a vertical axis, a cable chain, an offset
    in the current measurement): a constant residual whatever the motion."""
    name = "gravity_offset"
    correctable = True

    def _where(self, ctx):
        """(section, key, section values) of the constant force in the machine file."""
        if _rotary(ctx):
            return "mechanics", "external_torque_nm", ctx.cfg.mechanics
        return "table", "external_force_n", ctx.cfg.table

    def declared(self, ctx):
        _, key, values = self._where(ctx)
        f = getattr(values, key)
        return Term(self, {}, np.array([-f])) if f != 0.0 else None

    def propose(self, ctx, residual, model):
        r = residual[ctx.moving]
        s = np.sign(ctx.m.v[ctx.moving])
        up, down = r[s > 0], r[s < 0]
        ev = {"mean_residual": float(r.mean()),
              "mean_moving_plus": float(up.mean()) if up.size else 0.0,
              "mean_moving_minus": float(down.mean()) if down.size else 0.0}
        term = _linear_term(self, ctx, residual, ev)
        base = model.term(self.name)
        if base is not None:
            term.coef = term.coef + base.coef
        ev["text"] = (f"the residual has the same offset in both directions of motion "
                      f"({ev['mean_moving_plus']:+.3g} moving +, {ev['mean_moving_minus']:+.3g} "
                      f"moving -)")
        return term

    def columns(self, ctx, shape):
        return np.ones((ctx.rec.n, 1))

    def params(self, ctx, shape, coef):
        return {self._where(ctx)[1]: -float(coef[0])}

    def overrides(self, ctx, shape, coef, model):
        section, key, _ = self._where(ctx)
        return {section: {key: -float(coef[0])}}


class Stribeck(Effect):
    """The Stribeck dip: friction above the Coulomb level at low speed,
    (Fs - Fc) exp(-(v/vs)^2) sign(v)."""
    name = "stribeck"
    n_params = 2
    shape_keys = ("vs",)

    def _keys(self, ctx):
        if _rotary(ctx):
            return "breakaway_nm", "stribeck_velocity_rad_s"
        return "breakaway_n", "stribeck_velocity_m_s"

    def declared(self, ctx):
        k_fs, k_vs = self._keys(ctx)
        fs, vs = getattr(ctx.cfg.friction, k_fs), getattr(ctx.cfg.friction, k_vs)
        fc = getattr(ctx.cfg.friction, _coulomb_key(ctx))
        if vs <= 0 or fs <= fc:
            return None
        return Term(self, {"vs": vs}, np.array([fs - fc]))

    def propose(self, ctx, residual, model):
        # tried whatever Coulomb's residual looks like (a dip at low speed hides under a
        # level that is right on average), but not with the presliding spring, which
        # replaces Karnopp's stick-slip with Stribeck sliding friction in the plant
        if model.term("presliding_hysteresis") is not None:
            return None
        fit = self.dip_fit(ctx, residual, with_level=False)
        if fit is None:
            return None
        ex, vs, coef = fit
        ev = self.dip_evidence(ctx, residual, vs, ex)
        return Term(self, {"vs": vs}, coef, True, ev)

    def dip_fit(self, ctx: Context, residual: np.ndarray,
                with_level: bool) -> tuple[float, float, np.ndarray] | None:
        """The dip width that explains most of ``residual`` (N, shape (n,)) on the samples
        in motion: (share explained, vs in m/s or rad/s, coefficients); the coefficients
        are the excess Fs - Fc (N), or with ``with_level`` the Coulomb level Fc and the
        excess fitted together, both >= 0.  None when the widest dip tried fits best (no
        longer told apart from Coulomb's level) or the excess is 0."""
        vmax = float(np.max(np.abs(ctx.m.v[ctx.moving])))
        mask = ctx.moving
        best = None
        # a dip wider than a third of the top speed is no longer told apart from Coulomb:
        # one that fits best at the widest tried is no Stribeck dip
        widths = np.geomspace(vmax / 300.0, vmax / 3.0, 40)
        level = np.sign(ctx.m.v)[:, None]
        for vs in widths:
            col = self.columns(ctx, {"vs": vs})
            if with_level:
                col = np.hstack([level, col])
            k = col.shape[1]
            coef = lstsq(col, residual, mask, np.zeros(k), np.full(k, np.inf))
            ex = explained(residual, col @ coef, mask)
            if best is None or ex > best[0]:
                best = (ex, float(vs), coef)
        if best[1] == widths[-1] or best[2][-1] <= 0.0:
            return None
        return best

    def dip_evidence(self, ctx: Context, residual: np.ndarray, vs: float, ex: float) -> dict:
        """The dip's evidence: mean |residual| (N) below and above 2 vs, and a sentence."""
        mask = ctx.moving
        slow = mask & (np.abs(ctx.m.v) < 2 * vs)
        ev = {"explained": ex, "vs": vs,
              "mean_abs_residual_slow": float(np.mean(np.abs(residual[slow]))) if slow.any()
              else 0.0,
              "mean_abs_residual_fast": float(np.mean(np.abs(residual[mask & ~slow])))}
        ev["text"] = (f"friction above the Coulomb level at low speed: mean |residual| "
                      f"{ev['mean_abs_residual_slow']:.3g} below {2 * vs:.3g} against "
                      f"{ev['mean_abs_residual_fast']:.3g} above")
        return ev

    def columns(self, ctx, shape):
        v = ctx.m.v
        return (np.sign(v) * np.exp(-(v / shape["vs"]) ** 2))[:, None]

    def shape_label(self, ctx, key):
        return self._keys(ctx)[1]

    def bounds(self, shape):
        return np.zeros(1), np.full(1, np.inf)

    def params(self, ctx, shape, coef):
        k_fs, k_vs = self._keys(ctx)
        return {"static_minus_coulomb": float(coef[0]), k_vs: shape["vs"]}

    def overrides(self, ctx, shape, coef, model):
        k_fs, k_vs = self._keys(ctx)
        fc = model.term("coulomb_friction")
        level = float(fc.coef[0]) if fc is not None else 0.0
        return {"friction": {k_vs: shape["vs"], k_fs: level + float(coef[0])}}
