"""How far identification moved the machine file's declared coefficients, with their
uncertainty, against their tolerance (issue 13 part 4: refits without bias).

The refits hold every declared coefficient to a prior at its declared value
(:class:`hil.identify.model.Model`); what the data move anyway is listed here with its
standard uncertainty (from the last fit's Jacobian, the closed-loop refinement's where it
ran) and flagged when the change exceeds the coefficient's tolerance: a declared mass that
moves by 20 % is more likely absorbing an effect the model lacks than wrong by 20 %.
"""

import math

from hil.identify.model import Model


def declared_changes(model: Model) -> list[dict]:
    """One row per declared coefficient still in the model: ``parameter`` (the machine-file
    key, or ``effect[j]`` for a multi-coefficient term), ``declared``, ``identified``,
    ``sigma`` (standard uncertainty, NaN when unknown), ``change_pct`` (infinite from a
    declared 0, which has no per cent), ``tolerance_pct``,
    ``beyond_tolerance`` and ``significant`` (the change exceeds twice its uncertainty)."""
    rows = []
    for t in model.terms:
        c0 = model.declared.get(t.effect.name)
        if c0 is None or c0.size != t.coef.size or c0.size == 0:
            continue
        tol = model.tolerance_of(t.effect.name)
        for j in range(c0.size):
            before, after = float(c0[j]), float(t.coef[j])
            sigma = float(t.sigma[j]) if t.sigma is not None else math.nan
            label = f"{t.effect.name}[{j}]"
            if c0.size == 1:
                # the machine-file key and sign (a constant force is minus its coefficient)
                key, value0 = next(iter(t.effect.params(model.ctx, t.shape, c0).items()))
                _, value1 = next(iter(t.effect.params(model.ctx, t.shape, t.coef).items()))
                label, before, after = key, float(value0), float(value1)
            change = after - before
            rows.append({
                "parameter": label, "effect": t.effect.name, "declared": before,
                "identified": after, "sigma": sigma,
                "change_pct": (100.0 * change / abs(before) if before
                               else 0.0 if change == 0 else math.inf),
                "tolerance_pct": 100.0 * tol,
                "beyond_tolerance": abs(change) > tol * abs(before),
                "significant": None if math.isnan(sigma) else bool(abs(change) > 2.0 * sigma)})
    return rows


def change_text(row: dict) -> str:
    """A row of :func:`declared_changes` (or of report.json, where an infinite change is
    None) as words: "unchanged", "+12.5 %", or "n/a (declared 0)" where a per cent of the
    declared value does not exist."""
    before, after = row["declared"], row["identified"]
    if after == before:
        return "unchanged"
    if before == 0:
        return "n/a (declared 0)"
    return f"{100.0 * (after - before) / abs(before):+.3g} %"
