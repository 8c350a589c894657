"""The motor's holding brake (plant.effects.brake) against Newton's law on a rigid axis:
the LD386 linear motor (one mass: mover and table, 14.5 kg) with a 100 N brake, torque off,
pushed by a constant force (cogging left out).  Below the holding force it holds (the axis stays at rest);
above it, it slips and the axis accelerates at (F - F_brake - F_Coulomb - c v) / m, the
closed form integrated by hand; open, it does nothing.  A TLM machine with a brake is
refused (the projection needs the lumped solver's forces)."""

import math

import pytest

from plant import Plant
from plant import layout as L
from plant.config import load_machine
from plant.errors import ConfigError
from tests.conftest import CONFIGS

LD386 = CONFIGS / "ld386_linear.toml"
BRAKE_N = 100.0
MASS_KG = 14.5          # [motor] mass_kg 2.5 + [table] mass_kg 12
COULOMB_N = 18.26       # [friction] coulomb_n
VISCOUS_NS_M = 15.0     # [friction] viscous_ns_per_m
#: the motor's cogging force left out: its ripple is not in the closed form
NO_COGGING = {"cogging": {"amplitudes_n": [0.0, 0.0, 0.0]}}


def pushed(force_n: float, closed: bool, seconds: float) -> Plant:
    plant = Plant(load_machine(LD386, NO_COGGING | {"brake": {"holding_force_n": BRAKE_N}}),
                  table_pos=0.5)
    plant.inp[L.I_ENABLE] = 0.0
    plant.inp[L.I_BRAKE] = 1.0 if closed else 0.0
    plant.inp[L.I_LOAD] = force_n
    for _ in range(round(seconds * load_machine(LD386).motor.pwm_frequency_hz)):
        assert plant.step(plant.sub_per_pwm) == L.STATUS_OK
    return plant


@pytest.mark.parametrize("force_n", [50.0, -99.0])
def test_a_closed_brake_holds_a_force_below_its_level(force_n):
    plant = pushed(force_n, True, 0.5)
    assert plant.output("table_pos") == pytest.approx(0.5, abs=1e-9)
    assert plant.output("table_vel") == 0.0


def test_a_closed_brake_slips_under_a_larger_force_as_newton_says():
    """150 N against 100 N of brake and 18.26 N of Coulomb friction, viscous 15 N s/m:
    v(t) = v_inf (1 - exp(-t c / m)), v_inf = (F - F_b - F_c) / c."""
    t = 0.5
    plant = pushed(150.0, True, t)
    v_inf = (150.0 - BRAKE_N - COULOMB_N) / VISCOUS_NS_M
    expected = v_inf * (1.0 - math.exp(-t * VISCOUS_NS_M / MASS_KG))
    assert plant.output("table_vel") == pytest.approx(expected, rel=0.01)


def test_an_open_brake_does_nothing():
    t = 0.2
    plant = pushed(50.0, False, t)
    v_inf = (50.0 - COULOMB_N) / VISCOUS_NS_M
    expected = v_inf * (1.0 - math.exp(-t * VISCOUS_NS_M / MASS_KG))
    assert plant.output("table_vel") == pytest.approx(expected, rel=0.01)


def test_a_brake_on_the_tlm_solver_is_refused():
    with pytest.raises(ConfigError, match=r"\[brake\] holding 5 needs \[mechanics\] solver"):
        load_machine(CONFIGS / "tlm_rig.toml", {"brake": {"holding_torque_nm": 5.0}})
