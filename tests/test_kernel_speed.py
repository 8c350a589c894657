"""The kernel after the speed work of issue 12 part 7 (inlined effects, non-negative
offsets, no reference counting, the Stribeck cut-off) against the kernel before it, bit
for bit.

The reference (tests/data/kernel_reference.json, written by tests/kernel_reference.py
from the kernel as it was) holds state and outputs of every machine file in configs/ and
of an Arrow 500 X with pitch error, delay and backlash, under a stimulus that visits
current steps, a load, the power stage off, voltage mode and the Stribeck tail.  Also the
Stribeck cut-off on its own against math.exp.
"""

import json
import math

import numpy as np
import pytest

from plant import Plant
from plant import layout as L
from plant.effects.friction import STRIBECK_CUTOFF, sliding_friction
from tests.kernel_reference import REFERENCE, SNAPSHOT_EVERY, START_POS_M, cases, set_inputs

_REFERENCE = json.loads(REFERENCE.read_text())


@pytest.mark.parametrize("name", sorted(cases()))
def test_kernel_reproduces_the_original_kernel_bit_for_bit(name):
    """Every snapshot (state and outputs, every value's hex) as the original kernel."""
    ref = _REFERENCE[name]
    cfg, overrides = cases()[name]
    plant = Plant.from_file(cfg, table_pos=START_POS_M, overrides=overrides)
    assert plant.sub_per_pwm == ref["sub_per_pwm"]
    rng = np.random.default_rng(12)
    for k in range(len(ref["state"]) * SNAPSHOT_EVERY):
        set_inputs(k, plant, rng)
        plant.step(plant.sub_per_pwm)
        if (k + 1) % SNAPSHOT_EVERY == 0:
            snap = (k + 1) // SNAPSHOT_EVERY - 1
            assert [x.hex() for x in plant.state] == ref["state"][snap], f"call {k}"
            assert [x.hex() for x in plant.out] == ref["out"][snap], f"call {k}"


def _stribeck_params(vs: float) -> np.ndarray:
    p = np.zeros(L.P_COUNT)
    p[L.P_FR_VISCOUS] = 800.0
    p[L.P_FR_COULOMB] = 120.0
    p[L.P_FR_STATIC] = 160.0
    p[L.P_FR_STRIBECK_V] = vs
    return p


@pytest.mark.parametrize("vs", [1e-3, 2e-2, 1e-6])
def test_stribeck_cutoff_changes_no_bit(vs):
    """Sliding friction with the cut-off against the formula with math.exp everywhere,
    across the cut-off (|v|/v_s from 0 to 1e3, both signs): where exp underflows to
    exactly 0.0 the level is F_C either way."""
    p = _stribeck_params(vs)
    assert math.exp(-STRIBECK_CUTOFF) == 0.0
    ratios = np.concatenate([np.linspace(0.0, 40.0, 4001), np.geomspace(26.0, 1e3, 2001),
                             [math.sqrt(STRIBECK_CUTOFF) * (1 + d) for d in (-1e-15, 0, 1e-15)]])
    for v in np.concatenate([ratios * vs, -ratios * vs]):
        level = 120.0 + (160.0 - 120.0) * math.exp(-(v / vs) ** 2)
        visc = -800.0 * v - 0.0 * abs(v)
        expected = visc - level if v > 0.0 else (visc + level if v < 0.0 else 0.0)
        assert sliding_friction(p, v).hex() == expected.hex(), v
