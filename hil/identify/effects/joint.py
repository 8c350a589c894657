"""Candidates of two effects proposed together (issue 30, item 3).

Coulomb's level fitted alone to a residual that holds a Stribeck dip too takes the dip's
average: on a trace whose truth had both undeclared, Coulomb alone went far above the
truth's level and the joint refit of its domain cut the declared viscous friction to make
up for it (an outside trace: 332 N and -74 %; ours, tests/test_identify_shapes.py: -100 %),
after which the dip, proposed alone beside the wrong level, no longer gained.  So
wherever Coulomb's friction is a candidate, Coulomb with the Stribeck dip, the two fitted
together (level, excess Fs - Fc and width vs), is one too, ranked by the same held-out
criterion as every other candidate and judged the same way on the whole record.

A joint candidate's name joins its members' names with ``+``; it adds both terms at once.
"""

import numpy as np

from hil.identify.effects.base import Context, Term
from hil.identify.effects.force import CoulombFriction, Stribeck

COULOMB_STRIBECK = "coulomb_friction+stribeck"
#: joint candidate -> its members, the one that calls for it first
JOINT = {COULOMB_STRIBECK: ("coulomb_friction", "stribeck")}


def members(name: str) -> tuple[str, ...]:
    """The library effects a candidate adds: its members, or the effect itself."""
    return JOINT.get(name, (name,))


def domain_of(name: str, by_name: dict) -> str:
    """The residual domain of candidate ``name`` (its first member's)."""
    return by_name[members(name)[0]].domain


def companions(names: list[str], available) -> list[str]:
    """The joint candidates that ``names`` (this round's single candidates) call for: those
    whose first member is among them and whose other members ``available(name)`` allows."""
    return [j for j, (first, *rest) in JOINT.items()
            if first in names and all(available(r) for r in rest)]


def propose_coulomb_stribeck(ctx: Context, residual: np.ndarray, model,
                             coulomb: CoulombFriction, stribeck: Stribeck) -> list[Term] | None:
    """Coulomb's level and the Stribeck dip fitted together to the force residual (N,
    shape (n,)) with the model's own Coulomb term, if any, taken out of it (its level is
    fitted anew); None where the dip is not proposed (a presliding spring in the model,
    the widest dip fits best, no excess)."""
    if model.term("presliding_hysteresis") is not None:
        return None
    base = model.term(coulomb.name)
    target = residual + (base.contribution(ctx) if base is not None else 0.0)
    fit = stribeck.dip_fit(ctx, target, with_level=True)
    if fit is None:
        return None
    ex, vs, coef = fit
    ev = stribeck.dip_evidence(ctx, target, vs, ex)
    ev["text"] = (f"fitted with Coulomb's level: {coef[0]:.4g} + {coef[1]:.4g} at rest, dip "
                  f"width {vs:.3g}; " + ev["text"])
    return [Term(coulomb, {}, coef[:1].copy(), True, ev),
            Term(stribeck, {"vs": vs}, coef[1:].copy(), True, ev)]


def propose(name: str, ctx: Context, residual: np.ndarray | None, model,
            by_name: dict) -> list[Term] | None:
    """Propose candidate ``name`` (a library effect or a joint candidate) against its
    domain's ``residual``: its terms, or None when it proposes nothing."""
    if name == COULOMB_STRIBECK:
        return propose_coulomb_stribeck(ctx, residual, model, by_name["coulomb_friction"],
                                        by_name["stribeck"])
    term = by_name[name].propose(ctx, residual, model)
    return None if term is None else [term]
