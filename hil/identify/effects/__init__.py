"""The library of effects ``hil identify`` can name, each with the evidence that points to
it, its regressors and how it is written into a machine file (see ``base.Effect``)."""

from hil.identify.effects.base import FORCE, POSITION, REPLAY, Context, Effect, Term
from hil.identify.effects.delay import TimeDelay
from hil.identify.effects.drivetrain import Backlash, Compliance, Presliding
from hil.identify.effects.force import (
                                        CoulombFriction,
                                        GravityOffset,
                                        Inertia,
                                        Stribeck,
                                        ViscousAsymmetry,
                                        ViscousFriction,
)
from hil.identify.effects.periodic import Cogging, PitchError
from hil.identify.effects.screw_compliance import ScrewModelCompliance

#: every effect, simplest first: among effects that explain about as much, the earlier wins
LIBRARY: tuple[Effect, ...] = (
    Inertia(), ViscousFriction(), CoulombFriction(), GravityOffset(), ViscousAsymmetry(),
    Stribeck(), Cogging(), Presliding(), PitchError(), Backlash(), Compliance(),
    ScrewModelCompliance(), TimeDelay(),
)
NAMES = tuple(e.name for e in LIBRARY)
BY_NAME = {e.name: e for e in LIBRARY}

__all__ = ["FORCE", "POSITION", "REPLAY", "Context", "Effect", "Term", "LIBRARY", "NAMES",
           "BY_NAME"]
