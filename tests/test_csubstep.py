"""The C port of the sub-step (hil.bench.csubstep) against the numba kernel: the same
arrays in, the same bits out, call after call.

The two are independent implementations of the same equations in the same floating-point
order (C built without fused multiply-add), so any difference is a bug in one of them.
Skips, saying why, only when no C compiler is on PATH.
"""

import json

import numpy as np
import pytest

from hil.bench.csubstep import CStep, compiler, layout_header
from plant import Plant
from plant import layout as L
from tests.kernel_reference import REFERENCE, SNAPSHOT_EVERY, START_POS_M, cases, set_inputs

needs_cc = pytest.mark.skipif(compiler() is None, reason="no C compiler on PATH ($CC, cc or "
                              "gcc): the C port cannot be built (apt-get install gcc)")
#: the runs of the reference stimulus the C port covers (d-q motor, screw, lumped solver)
C_CASES = ("arrow500_x", "arrow500_x_effects", "arrow500_x_screw_friction")


@pytest.fixture(scope="module")
def cstep():
    return CStep()


def _pair(name):
    cfg, overrides = cases()[name]
    return (Plant.from_file(cfg, table_pos=START_POS_M, overrides=overrides),
            Plant.from_file(cfg, table_pos=START_POS_M, overrides=overrides))


@needs_cc
@pytest.mark.parametrize("name", C_CASES)
def test_c_port_matches_the_kernel_bit_for_bit(cstep, name):
    """Every call of the reference stimulus (current steps, load, power stage off, voltage
    mode, a long push into the Stribeck tail): state, outputs and status identical."""
    numba_plant, c_plant = _pair(name)
    assert cstep.supports(c_plant.params)
    rng_numba, rng_c = np.random.default_rng(12), np.random.default_rng(12)
    for k in range(600):
        set_inputs(k, numba_plant, rng_numba)
        set_inputs(k, c_plant, rng_c)
        status = numba_plant.step(numba_plant.sub_per_pwm)
        c_status = cstep.axis_step(c_plant.params, c_plant.state, c_plant.inp, c_plant.out,
                                   c_plant.sub_per_pwm)
        assert c_status == status
        np.testing.assert_array_equal(c_plant.state, numba_plant.state, err_msg=f"call {k}")
        np.testing.assert_array_equal(c_plant.out, numba_plant.out, err_msg=f"call {k}")


@needs_cc
@pytest.mark.parametrize("name", C_CASES)
def test_c_port_reproduces_the_stored_reference(cstep, name):
    """The C port against the trajectory the original kernel wrote (tests/data)."""
    ref = json.loads(REFERENCE.read_text())[name]
    _, plant = _pair(name)
    rng = np.random.default_rng(12)
    for k in range(len(ref["state"]) * SNAPSHOT_EVERY):
        set_inputs(k, plant, rng)
        cstep.axis_step(plant.params, plant.state, plant.inp, plant.out, plant.sub_per_pwm)
        if (k + 1) % SNAPSHOT_EVERY == 0:
            snap = (k + 1) // SNAPSHOT_EVERY - 1
            assert [x.hex() for x in plant.state] == ref["state"][snap], f"call {k}"
            assert [x.hex() for x in plant.out] == ref["out"][snap], f"call {k}"


@needs_cc
def test_c_port_reports_a_nonfinite_state_as_the_kernel_does(cstep):
    """A NaN in the state gives STATUS_NONFINITE from both."""
    numba_plant, c_plant = _pair("arrow500_x")
    for plant in (numba_plant, c_plant):
        plant.state[L.S_TABLE_V] = np.nan
    assert numba_plant.step(1) == L.STATUS_NONFINITE
    assert cstep.axis_step(c_plant.params, c_plant.state, c_plant.inp, c_plant.out,
                           1) == L.STATUS_NONFINITE


@needs_cc
@pytest.mark.parametrize("config", ["emps", "tlm_rig", "geiss_c_axis"])
def test_c_port_declines_models_it_does_not_carry(cstep, configs_dir, config):
    """First-order and commutation motors, rigid mechanics and the TLM solver: not ported."""
    assert not cstep.supports(Plant.from_file(configs_dir / f"{config}.toml").params)


def test_layout_header_carries_every_index():
    """The header defines the layout's indices with their values (no drift possible)."""
    header = layout_header()
    for name in ("P_DT", "S_TABLE_X", "I_IQ_REF", "O_INDEX", "P_COUNT", "MOTOR_DQ",
                 "STATUS_NONFINITE"):
        assert f"#define {name} {getattr(L, name)}\n" in header
