"""How far identification moved the machine file's declared values, with their
uncertainty, against their tolerance (issue 13 part 4: refits without bias).

The refits hold every declared value (coefficients and scalar shapes) to a prior at its
declared value and within its tolerance (:class:`hil.identify.model.Model`); what the
data move anyway is listed here with its standard uncertainty (from the last fit's
Jacobian, the closed-loop refinement's where it ran), and what they ask for beyond the
tolerance is a finding, not taken (issue 30, item 3): a declared mass that would move by
20 % is more likely absorbing an effect the model lacks than wrong by 20 %, and a fault's
diagnosis (:mod:`hil.identify.diagnosis`) reads the change asked for.
"""

import math

import numpy as np

from hil.identify.model import Model


def declared_changes(model: Model) -> list[dict]:
    """One row per declared value still in the model, coefficients and scalar shapes alike
    (``Term.values``: the Stribeck velocity, the presliding spring's stiffness, x1 and
    exponent): ``parameter`` (the machine-file key, or ``effect[j]`` for a coefficient of
    a multi-coefficient term whose coefficients are not one key each), ``declared``,
    ``identified`` (the value taken, within the tolerance), ``sigma`` (standard
    uncertainty, NaN when unknown), ``change_pct`` (of the value taken; infinite from a
    declared 0, which has no per cent), ``tolerance_pct``, ``wanted`` (what the data ask
    for where that lies beyond the tolerance, else None) with ``wanted_change_pct`` and
    ``wanted_by``, ``beyond_tolerance`` (the value asked for lies outside the declared
    box, :meth:`~hil.identify.effects.base.Effect.declared_box`: a finding) and
    ``significant`` (the change taken exceeds twice its uncertainty).  The one
    coefficient of a term that is a fixed scale of its shape (the presliding spring's)
    has no row of its own: its key is a shape's."""
    rows = []
    for t in model.terms:
        c0 = model.declared_of(t)
        if c0 is None or c0.size == 0:
            continue
        tol = model.tolerance_of(t.effect.name)
        box_lo, box_hi = t.effect.declared_box(c0, tol)
        values = t.values()
        c_asked = t.wanted if t.wanted is not None else values
        k = t.coef.size
        keyed = k == 1 or t.effect.keys_per_coefficient
        for j in range(c0.size):
            if math.isnan(c0[j]):
                # not declared (a coefficient the fit adds beside declared ones, a shape
                # the declaration lacks: Effect.declared_for)
                continue
            if j < k and t.effect.fixed_scale:
                continue
            sigma = float(t.sigma[j]) if t.sigma is not None and j < t.sigma.size else math.nan
            if j < k and not keyed:
                label = f"{t.effect.name}[{j}]"
                before, after = float(c0[j]), float(values[j])
                wanted = float(t.wanted[j]) if t.wanted is not None else None
            else:
                # the machine-file key and sign (a constant force is minus its coefficient,
                # a stiffness the inverse of a compliance, the presliding stiffness k1
                # times its scale)
                label = (list(_params_at(model, t, c0))[j] if j < k
                         else t.effect.shape_label(model.ctx,
                                                   t.effect.shape_keys_of(t.shape)[j - k]))
                before = _params_at(model, t, c0)[label]
                after = _params_at(model, t, values)[label]
                wanted = (_params_at(model, t, t.wanted)[label] if t.wanted is not None
                          else None)
                sigma *= _key_slope(model, t, j, label)
            # the box's edges are where a held value sits: a hair beyond is rounding
            slack = 1e-9 * abs(float(c0[j]))
            if c0[j] == 0.0:
                beyond = c_asked[j] != 0.0
            else:
                beyond = not box_lo[j] - slack <= c_asked[j] <= box_hi[j] + slack
            # a term holds what was asked for all its values: a row's is a finding only
            # where it lies beyond the row's own tolerance
            wanted = wanted if beyond else None
            change = after - before
            asked = (wanted if wanted is not None else after) - before
            rows.append({
                "parameter": label, "effect": t.effect.name, "declared": before,
                "identified": after, "sigma": sigma, "change_pct": _pct(change, before),
                "tolerance_pct": 100.0 * tol, "wanted": wanted,
                "wanted_change_pct": None if wanted is None else _pct(asked, before),
                "wanted_by": t.wanted_by if wanted is not None else "",
                "beyond_tolerance": bool(beyond),
                "significant": None if math.isnan(sigma) else bool(abs(change) > 2.0 * sigma)})
    return rows


def _params_at(model: Model, term, values) -> dict:
    """``term``'s physical parameters (:meth:`~hil.identify.effects.base.Effect.params`,
    name -> value) with its values set to ``values`` (laid out as ``Term.values``)."""
    k = term.coef.size
    keys = term.effect.shape_keys_of(term.shape)
    shape = {**term.shape, **{key: float(v) for key, v in zip(keys, values[k:])}}
    return {name: float(v) for name, v in
            term.effect.params(model.ctx, shape, np.asarray(values[:k])).items()
            if not isinstance(v, list)}


#: relative step of the value that :func:`_key_slope` differentiates with
SLOPE_STEP = 1e-6


def _key_slope(model: Model, term, j: int, label: str) -> float:
    """|d key / d value j| at ``term``'s values: what carries a value's uncertainty to its
    key's, ``label`` (1 for a key that is the value, k/c for a stiffness k that is the
    inverse of a compliance c)."""
    values = term.values()
    h = SLOPE_STEP * max(abs(float(values[j])), 1e-300)
    moved = values.copy()
    moved[j] += h
    return abs(_params_at(model, term, moved)[label] - _params_at(model, term, values)[label]) / h


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
