"""Cogging harmonics from the slot and pole numbers (issue 14 part 5): with [cogging] slots the
cogging's fundamental is LCM(slots, 2 p) cycles per mechanical revolution and its orders are
multiples of it.

Against the textbook formula (recomputed here from the slot and pole pitches' symmetries, without
an LCM), hand values, and the FFT of the cogging torque the kernel produces over one
revolution of a rotor turned at constant speed.
"""

import math

import numpy as np
import pytest

from plant import Plant
from plant import layout as L
from plant.cogging_orders import cogging_fundamental
from plant.config import load_machine
from plant.errors import ConfigError
from tests.test_plant_modulation import CONFIGS, HELD_MOTOR


def per_revolution_by_pitches(slots: int, pole_pairs: int) -> int:
    """Cogging cycles per mechanical revolution from the symmetries: the cogging torque
    repeats after a slot pitch (1/slots revolution, the stator maps onto itself) and after
    a pole pitch (1/(2p), the magnets do, up to a polarity cogging does not see), hence after
    every whole combination of the two; its period is the smallest positive one."""
    period = min(abs(a / slots - b / (2 * pole_pairs))
                 for a in range(slots + 1) for b in range(2 * pole_pairs + 1)
                 if abs(a / slots - b / (2 * pole_pairs)) > 1e-12)
    return round(1.0 / period)


@pytest.mark.parametrize("slots, pairs", [(36, 3), (9, 4), (12, 5), (12, 4), (24, 11),
                                          (48, 22), (18, 8), (6, 2)])
def test_the_fundamental_is_the_slot_and_pole_pitches_common_multiple(slots, pairs):
    assert cogging_fundamental(slots, pairs) * pairs == pytest.approx(
        per_revolution_by_pitches(slots, pairs), rel=1e-15)


def test_hand_values():
    """36 slots, 6 poles: 36 per revolution, 12 per electrical revolution; 9 slots, 8 poles:
    72 and 18; 12 slots, 10 poles: 60 and 12."""
    assert cogging_fundamental(36, 3) == 12.0
    assert cogging_fundamental(9, 4) == 18.0
    assert cogging_fundamental(12, 5) == 12.0


def test_the_arrow_cogs_at_its_slot_harmonics():
    """The Arrow 500 X: 36 slots, six poles: orders 12 and 24 (no longer 6, issue 14)."""
    cfg = load_machine(CONFIGS / "arrow500_x.toml")
    assert cfg.cogging.slots == 36 and cfg.cogging.orders == (12.0, 24.0)


def test_without_orders_the_slots_give_the_first_multiples():
    cfg = load_machine(CONFIGS / "arrow500_x.toml",
                       {"cogging": {"orders": [], "amplitudes_nm": [0.1, 0.05, 0.02],
                                    "phases_deg": []}})
    assert cfg.cogging.orders == (12.0, 24.0, 36.0)


@pytest.mark.parametrize("orders", [[6.0, 12.0], [12.0, 18.0], [4.0, 12.0]])
def test_an_order_that_is_no_slot_harmonic_is_refused_naming_the_fundamental(orders):
    with pytest.raises(ConfigError, match=r"\[cogging\] orders = .* no cogging harmonic of 36 "
                                          r"slots and 6 poles.*LCM\(36, 6\) / 3 = 12"):
        load_machine(CONFIGS / "arrow500_x.toml", {"cogging": {"orders": orders}})


def test_slots_need_a_whole_number_of_pole_pairs(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(HELD_MOTOR.format(modulation="").replace("pole_pairs = 3",
                                                             "pole_pairs = 3.5")
                    + "\n[cogging]\nslots = 36\namplitudes_nm = [0.1]\n")
    with pytest.raises(ConfigError, match="whole number of .motor. pole_pairs"):
        load_machine(path)


def test_fft_of_the_kernels_cogging_over_one_revolution(tmp_path):
    """9 slots, 8 poles (72 cycles per revolution), two amplitudes: the rotor turned at
    constant speed with the power stage off (the torque is the cogging alone), 1024 samples
    over one revolution: lines at 72 and 144 per revolution with the configured amplitudes,
    every other line below 1e-9 of them."""
    amps = (0.1, 0.04)
    path = tmp_path / "slots.toml"
    path.write_text(HELD_MOTOR.format(modulation="").replace("pole_pairs = 3", "pole_pairs = 4")
                    + f"\n[cogging]\nslots = 9\namplitudes_nm = {list(amps)}\n"
                    "phases_deg = [20.0, -50.0]\n")
    plant = Plant.from_file(path)
    assert plant.config.cogging.orders == (18.0, 36.0)
    n = 1024
    omega = 2.0 * math.pi / (n * plant.pwm_period)
    nr, ro = int(plant.params[L.P_N_ROT]), int(plant.params[L.P_SOFF_ROT])
    plant.state[ro + nr:ro + 2 * nr] = omega
    plant.set_input(enable=0.0)
    torque = plant.run(n, plant.sub_per_pwm)["torque"]
    line = np.abs(np.fft.rfft(torque)) * 2.0 / n
    assert line[72] == pytest.approx(amps[0], rel=1e-6)
    assert line[144] == pytest.approx(amps[1], rel=1e-6)
    others = np.delete(line, [72, 144])
    assert others.max() < 1e-9 * amps[0]
