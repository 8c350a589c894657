"""How far identification moved the machine file's declared coefficients, with their
uncertainty, against their tolerance (issue 13 part 4: refits without bias).

The refits hold every declared coefficient to a prior at its declared value and within
its tolerance (:class:`hil.identify.model.Model`); what the data move anyway is listed
here with its standard uncertainty (from the last fit's Jacobian, the closed-loop
refinement's where it ran), and what they ask for beyond the tolerance is a finding, not
taken (issue 30, item 3): a declared mass that would move by 20 % is more likely
absorbing an effect the model lacks than wrong by 20 %, and a fault's diagnosis
(:mod:`hil.identify.diagnosis`) reads the change asked for.
"""

import math

from hil.identify.model import Model


def declared_changes(model: Model) -> list[dict]:
    """One row per declared coefficient still in the model: ``parameter`` (the machine-file
    key, or ``effect[j]`` for a multi-coefficient term whose coefficients are not one key
    each), ``declared``, ``identified`` (the
    value taken, within the tolerance), ``sigma`` (standard uncertainty, NaN when
    unknown), ``change_pct`` (of the value taken; infinite from a declared 0, which has no
    per cent), ``tolerance_pct``, ``wanted`` (what the data ask for where that lies beyond
    the tolerance, else None) with ``wanted_change_pct`` and ``wanted_by``,
    ``beyond_tolerance`` (the coefficient asked for lies outside the declared box,
    :meth:`~hil.identify.effects.base.Effect.declared_box`: a finding) and
    ``significant`` (the change taken exceeds twice its uncertainty)."""
    rows = []
    for t in model.terms:
        c0 = model.declared_of(t)
        if c0 is None or c0.size != t.coef.size or c0.size == 0:
            continue
        tol = model.tolerance_of(t.effect.name)
        box_lo, box_hi = t.effect.declared_box(c0, tol)
        c_asked = t.wanted if t.wanted is not None else t.coef
        keyed = c0.size == 1 or t.effect.keys_per_coefficient
        for j in range(c0.size):
            if math.isnan(c0[j]):
                # not declared (a coefficient the fit adds beside declared ones)
                continue
            before, after = float(c0[j]), float(t.coef[j])
            sigma = float(t.sigma[j]) if t.sigma is not None else math.nan
            wanted = float(t.wanted[j]) if t.wanted is not None else None
            label = f"{t.effect.name}[{j}]"
            if keyed:
                # the machine-file key and sign (a constant force is minus its coefficient,
                # a stiffness the inverse of a compliance)
                label, before = _key_value(model, t, c0, j)
                after = _key_value(model, t, t.coef, j)[1]
                sigma *= _key_slope(model, t, j)
                if wanted is not None:
                    wanted = _key_value(model, t, t.wanted, j)[1]
            change = after - before
            asked = (wanted if wanted is not None else after) - before
            # the box's edges are where a held coefficient sits: a hair beyond is rounding
            slack = 1e-9 * abs(float(c0[j]))
            if c0[j] == 0.0:
                beyond = c_asked[j] != 0.0
            else:
                beyond = not box_lo[j] - slack <= c_asked[j] <= box_hi[j] + slack
            rows.append({
                "parameter": label, "effect": t.effect.name, "declared": before,
                "identified": after, "sigma": sigma, "change_pct": _pct(change, before),
                "tolerance_pct": 100.0 * tol, "wanted": wanted,
                "wanted_change_pct": None if wanted is None else _pct(asked, before),
                "wanted_by": t.wanted_by if wanted is not None else "",
                "beyond_tolerance": bool(beyond),
                "significant": None if math.isnan(sigma) else bool(abs(change) > 2.0 * sigma)})
    return rows


def _key_value(model: Model, term, coef, j: int) -> tuple[str, float]:
    """The machine-file key of ``term``'s coefficient ``j`` and its value for ``coef``."""
    key, value = list(term.effect.params(model.ctx, term.shape, coef).items())[j]
    return key, float(value)


#: relative step of the coefficient that :func:`_key_slope` differentiates with
SLOPE_STEP = 1e-6


def _key_slope(model: Model, term, j: int) -> float:
    """|d key / d coefficient j| at ``term``'s coefficients: what carries a coefficient's
    uncertainty to its key's (1 for a key that is the coefficient, k/c for a stiffness k
    that is the inverse of a compliance c)."""
    h = SLOPE_STEP * max(abs(float(term.coef[j])), 1e-300)
    moved = term.coef.copy()
    moved[j] += h
    return abs(_key_value(model, term, moved, j)[1] - _key_value(model, term, term.coef, j)[1]) / h


def _pct(change: float, before: float) -> float:
    return 100.0 * change / abs(before) if before else 0.0 if change == 0 else math.inf


def asked_pct(row: dict) -> float | None:
    """The change in per cent the data ask for: beyond the tolerance, what a row of
    :func:`declared_changes` holds as ``wanted``; else the change taken."""
    return row["wanted_change_pct"] if row.get("wanted") is not None else row["change_pct"]


def asked_text(row: dict) -> str:
    """:func:`change_text` of the change the data ask for."""
    if row.get("wanted") is None:
        return change_text(row)
    return change_text({**row, "identified": row["wanted"]})


def finding_text(row: dict) -> str:
    """A row whose change asked for lies beyond its tolerance, as the report's finding:
    "mass_kg would move +12 % (tolerance 10 %, asked for by the joint refit of its
    domain): a finding, not taken; taken: +10 %"."""
    by = f", asked for by {row['wanted_by']}" if row.get("wanted_by") else ""
    return (f"{row['parameter']} would move {asked_text(row)} (tolerance "
            f"{row['tolerance_pct']:g} %{by}): a finding, not taken; taken: "
            f"{change_text(row)}")


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
