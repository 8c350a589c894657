"""The plant's reference sensors for homing (plant.effects.reference): the home switch on
the table and the encoder's index marks.

References, from the machine files alone: the Arrow 500 X's 10 mm lead and 4194304
increments per motor revolution (one index mark per revolution; the switch's edge half a
lead above the start of the travel, between the marks at 0 and 10 mm); the LD386 linear
motor's 30 mm pole pitch and 78.125 nm scale (a mark per electrical period of two pole
pitches: every 768000 increments, the edge at 30 mm).
"""

import math

import pytest

from plant import OUTPUTS, Plant
from plant import layout as L
from plant.config import load_machine
from tests.conftest import CONFIGS


def sensors(config, x: float) -> tuple[float, float, float]:
    """(home switch, index marks, encoder counts) with the table at rest at ``x``."""
    plant = Plant(load_machine(CONFIGS / config), table_pos=x)
    plant.inp[L.I_ENABLE] = 0.0
    plant.step(plant.sub_per_pwm)
    return (plant.output("home_switch"), plant.output("index_marks"),
            plant.output("encoder_counts"))


@pytest.mark.parametrize("config, edge_m, per_mark", [
    ("arrow500_x.toml", 0.005, 4194304),
    ("ld386_linear.toml", 0.030, round(0.060 / 7.8125e-8)),
])
def test_the_switch_is_on_below_its_edge_and_the_marks_count_revolutions(config, edge_m,
                                                                          per_mark):
    assert Plant(load_machine(CONFIGS / config)).counts_per_mark == per_mark
    for x, switch in ((edge_m - 1e-4, 1.0), (edge_m + 1e-4, 0.0), (-0.002, 1.0),
                      (0.3, 0.0)):
        on, marks, counts = sensors(config, x)
        assert on == switch, x
        assert marks == math.floor(counts / per_mark), x
    assert sensors(config, -0.001)[1] == -1.0 and sensors(config, 0.001)[1] == 0.0
    assert sensors(config, 2 * edge_m + 0.001)[1] == 1.0


def test_a_rotary_table_has_the_switch_on_half_a_turn():
    config = "geiss_c_axis.toml"
    edge = Plant(load_machine(CONFIGS / config)).params[L.P_HOME_SWITCH]
    turn = 2 * math.pi
    offsets = (-0.1, 0.1, turn / 2 - 0.1, turn / 2 + 0.1, turn - 0.1, turn + 0.1)
    ons = [sensors(config, edge + d)[0] for d in offsets]
    assert ons == [1.0, 0.0, 0.0, 1.0, 1.0, 0.0]  # on over (edge - pi, edge), each turn


def test_the_outputs_are_named():
    assert OUTPUTS["home_switch"] == L.O_HOME_SWITCH
    assert OUTPUTS["index_marks"] == L.O_INDEX
