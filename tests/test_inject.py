"""Fault and wear injection (issue 14 part 6): the ``[inject]`` tables, the flags, the
schedule (steps and ramps against their straight-line formula), what each fault writes
into the plant's parameters, the lock-step simulation and ``hil sim``'s trace header,
and the INJECT message of the msgpack links over real sockets."""

import math
import socket

import numpy as np
import pytest

from hil.inject import FAULT_NAMES, INJECT_HELP
from hil.inject.catalog import FAULTS
from hil.inject.schedule import Injector, from_flags, from_machine, parse_flag
from io_adapters import Setpoint, open_endpoint
from io_adapters.codec import KIND_INJECT, encode_inject
from io_adapters.messages import InjectRequest
from plant import Plant
from plant import layout as L
from plant.config import load_machine
from plant.errors import ConfigError
from tests.conftest import CONFIGS

ARROW = CONFIGS / "arrow500_x.toml"
LD386 = CONFIGS / "ld386_linear.toml"


def arrow(inject: dict | None = None):
    return load_machine(ARROW, {"inject": inject} if inject else None)


def test_the_catalog_is_the_one_the_command_line_and_canopen_name():
    """The flag's help and 2F00h's sub-indices follow the catalog's order; every fault's
    table has its level key and the two timing keys."""
    assert tuple(FAULTS) == FAULT_NAMES
    for name, f in FAULTS.items():
        assert name in INJECT_HELP
        keys = set(f.section.__dataclass_fields__)
        assert {f.level_key, "at_s", "ramp_s"} <= keys, name


@pytest.mark.parametrize("table, message", [
    ({"wear": {"growth_pct": 5}}, "unknown fault [inject.wear]"),
    ({"friction_growth": {"growth": 5}}, "unknown key [inject.friction_growth] growth"),
    ({"friction_growth": {}}, "missing key [inject.friction_growth] growth_pct (unit %)"),
    ({"preload_loss": {"loss_pct": 95}}, "[inject.preload_loss] loss_pct = 95"),
    ({"friction_growth": {"growth_pct": 5, "ramp_s": -1}}, "ramp_s = -1"),
    ({"friction_growth": 3}, "[inject.friction_growth] must be a table"),
])
def test_a_bad_inject_table_is_refused_naming_the_file_table_and_key(table, message):
    with pytest.raises(ConfigError) as err:
        from_machine(arrow(table))
    assert message in str(err.value) and str(ARROW) in str(err.value)


def test_a_nut_fault_on_a_linear_motor_is_refused_before_start():
    cfg = load_machine(LD386, {"inject": {"backlash_growth": {"growth_m": 1e-5}}})
    with pytest.raises(ConfigError, match=r"\[inject.backlash_growth\] needs a ball-screw nut"):
        from_machine(cfg)


@pytest.mark.parametrize("flag, message", [
    ("friction_growth", "expected FAULT:KEY=VALUE"),
    ("friction_growth:growth_pct", "is not KEY=NUMBER"),
    ("friction_growth:growth_pct=x", "is not KEY=NUMBER"),
    ("Y/friction_growth:growth_pct=5", "no axis 'Y'"),
])
def test_a_bad_flag_is_refused_saying_how_to_write_it(flag, message):
    with pytest.raises(ConfigError, match=message):
        from_flags([flag], arrow())


def test_the_flag_is_the_table_in_one_line():
    assert parse_flag("torque_ripple:ripple_pct=5,order=3,at_s=0.5") == (
        "torque_ripple", {"ripple_pct": 5.0, "order": 3.0, "at_s": 0.5})


def test_a_ramp_grows_on_its_straight_line_and_a_later_injection_takes_over():
    """friction_growth 50 % from 1 s over 2 s: the Coulomb force follows
    base (1 + 0.5 min(1, (t - 1)/2)); then a request ramps it back to 0 over 1 s from
    the level it has reached; events say what happened."""
    cfg = arrow({"friction_growth": {"growth_pct": 50, "at_s": 1.0, "ramp_s": 2.0}})
    plant = Plant(cfg)
    base = plant.params[L.P_FR_COULOMB]
    inj = Injector(plant.params, cfg, from_machine(cfg))
    for t in (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 3.5):
        if inj.busy:
            inj.update(t)
        share = min(1.0, max(0.0, (t - 1.0) / 2.0))
        assert plant.params[L.P_FR_COULOMB] == pytest.approx(base * (1 + 0.5 * share),
                                                             rel=1e-12), t
    assert not inj.busy
    assert [e.kind for e in inj.events] == ["injected", "reached"]
    inj.request("friction_growth", {"growth_pct": 0.0, "ramp_s": 1.0}, "test")
    inj.update(4.0)
    inj.update(4.5)
    assert plant.params[L.P_FR_COULOMB] == pytest.approx(base * 1.25, rel=1e-12)
    inj.update(5.0)
    assert plant.params[L.P_FR_COULOMB] == pytest.approx(base, rel=1e-12)
    assert inj.state() == {}
    inj.request("friction_growth", {"growth_pct": 5000.0}, "adapter")
    inj.update(6.0)
    assert inj.events[-1].kind == "refused" and "growth_pct = 5000" in inj.events[-1].reason


#: fault -> (table, {param index: expected value as a function of the healthy params})
WRITES = {
    "friction_growth": ({"growth_pct": 40}, {L.P_FR_COULOMB: lambda b: 1.4 * b[L.P_FR_COULOMB],
                                             L.P_FR_STATIC: lambda b: 1.4 * b[L.P_FR_STATIC],
                                             L.P_FR_VISCOUS: lambda b: 1.4 * b[L.P_FR_VISCOUS]}),
    "backlash_growth": ({"growth_m": 2e-5}, {L.P_NUT_GAP: lambda b: b[L.P_NUT_GAP] + 2e-5}),
    "preload_loss": ({"loss_pct": 30}, {L.P_NUT_K: lambda b: 0.7 * b[L.P_NUT_K]}),
    "torque_constant_loss": ({"loss_pct": 10}, {L.P_KT: lambda b: 0.9 * b[L.P_KT],
                                                L.P_PSI: lambda b: 0.9 * b[L.P_PSI]}),
    "encoder_noise": ({"noise_counts": 3}, {L.P_ENC_NOISE: lambda b: 3.0}),
    "encoder_lost_counts": ({"lost_ppm": 20}, {L.P_ENC_LOST: lambda b: 2e-5}),
    "current_offset": ({"offset_a": 0.2}, {L.P_I_OFFSET: lambda b: 0.2}),
    "current_gain_error": ({"gain_error_pct": 3}, {L.P_I_GAIN_ERR: lambda b: 0.03}),
    "torque_ripple": ({"ripple_pct": 4, "order": 3, "phase_deg": 90},
                      {L.P_RIPPLE_AMP: lambda b: 0.04, L.P_RIPPLE_ORDER: lambda b: 3.0,
                       L.P_RIPPLE_PHASE: lambda b: math.pi / 2}),
}


@pytest.mark.parametrize("fault", FAULT_NAMES)
def test_each_fault_writes_its_parameters_and_nothing_else(fault):
    """The parameters each fault owns take their values (the catalog's formulas, written
    out here again); every other parameter keeps its healthy value but the fault switch."""
    table, expected = WRITES[fault]
    cfg = arrow({fault: table})
    plant = Plant(cfg)
    base = plant.params.copy()
    Injector(plant.params, cfg, from_machine(cfg)).update(0.0)
    for index, value in expected.items():
        assert plant.params[index] == pytest.approx(value(base), rel=1e-12, abs=1e-15), index
    changed = set(np.flatnonzero(plant.params != base)) - {L.P_FAULTS}
    assert changed <= set(expected), f"{fault} also wrote {changed - set(expected)}"
    sensor = fault in ("encoder_noise", "encoder_lost_counts", "current_offset",
                       "current_gain_error", "torque_ripple")
    assert plant.params[L.P_FAULTS] == (1.0 if sensor else base[L.P_FAULTS])


def test_a_machine_file_fault_acts_in_the_lockstep_simulation_from_its_time():
    """friction_growth +100 % at 0.05 s in a lock-step run holding the axis: the Coulomb
    force is the healthy one before and twice it after."""
    from hil.sim import LockStep
    cfg = arrow()
    ls = LockStep(cfg, 0.25, inject=["friction_growth:growth_pct=100,at_s=0.05"])
    base = ls.plant.params[L.P_FR_COULOMB]
    ls.enable()
    assert ls.plant.params[L.P_FR_COULOMB] == base
    ls.run(0.06)
    assert ls.plant.params[L.P_FR_COULOMB] == pytest.approx(2.0 * base, rel=1e-12)
    assert ls.injectors[0].events[0].kind == "injected"


def test_hil_sim_names_every_injection_in_the_trace_header(tmp_path):
    from hil.commands import run_sim
    from hil.trace_file import read_trace
    program = tmp_path / "p.nc"
    program.write_text("G90 G01 X252 F3000\nM30\n")
    summary = run_sim(ARROW, program, tmp_path / "out", 250.0, None, None,
                      inject=("encoder_noise:noise_counts=2,at_s=0.01",))
    meta = read_trace(tmp_path / "out" / "trace.csv").metadata
    assert meta["injected_1"].startswith("encoder_noise noise_counts=2 at 0.01 s (--inject)")
    assert any("injected" in line for line in summary["injections"])


def _udp_pair():
    device = open_endpoint("udp://127.0.0.1:0", "device")
    ctrl = open_endpoint(f"udp://127.0.0.1:{device.address[1]}", "controller")
    return device, ctrl


def test_an_inject_message_reaches_the_device_from_its_peer_only():
    """Real sockets on 127.0.0.1: the controller's INJECT (its HELLO pinned it) is handed
    on, settings as floats; from another socket, with a NaN, or malformed, it is counted
    as such and dropped; the frame counts add up.  A device with no peer yet takes none
    (a bare socket's INJECT is foreign)."""
    device, ctrl = _udp_pair()
    stranger = open_endpoint(f"udp://127.0.0.1:{device.address[1]}", "controller")
    try:
        sp = Setpoint()
        request = InjectRequest(0, "friction_growth", {"growth_pct": 50, "ramp_s": 2.5})
        ctrl.send_setpoint(sp)
        assert device.recv_setpoint(sp, 1.0)
        ctrl.send_injection(request)
        stranger.send_injection(request)
        ctrl.send_injection(InjectRequest(0, "friction_growth", {"growth_pct": math.nan}))
        ctrl._send_message(b"\x97\x01\x05", None)  # an INJECT cut short
        for _ in range(20):
            device.recv_setpoint(sp, 0.05)
        assert device.injections == [InjectRequest(0, "friction_growth",
                                                   {"growth_pct": 50.0, "ramp_s": 2.5})]
        s = device.stats
        assert (s.injections, s.refused_nonfinite, s.malformed) == (1, 1, 1)
        assert s.frames == (s.received + s.malformed + s.refused_nonfinite + s.refused_mode
                            + s.refused_range + s.duplicates + s.out_of_order + s.foreign
                            + s.stale_session + s.handshakes + s.injections)
    finally:
        for ep in (device, ctrl, stranger):
            ep.close()
    lonely = open_endpoint("udp://127.0.0.1:0", "device")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
            raw.sendto(encode_inject(7, 0, request), ("127.0.0.1", lonely.address[1]))
            for _ in range(10):
                lonely.recv_setpoint(sp, 0.05)
        assert (lonely.injections, lonely.stats.foreign) == ([], 1)
    finally:
        lonely.close()


@pytest.mark.parametrize("request_, message", [
    (InjectRequest(0, "", {"a": 1.0}), "fault=''"),
    (InjectRequest(0, "x" * 41, {"a": 1.0}), "expected a name"),
    (InjectRequest(0, "f", {}), "expected a map of 1-8"),
    (InjectRequest(0, "f", {"a": "1"}), "expected a name and a number"),
    (InjectRequest(256, "f", {"a": 1.0}), "axis=256"),
])
def test_an_inject_that_does_not_fit_the_layout_is_not_sent(request_, message):
    from io_adapters import FrameError
    with pytest.raises(FrameError, match=message):
        encode_inject(1, 0, request_)
    assert KIND_INJECT == 5


def test_hil_controller_checks_its_injections_before_start_and_sends_them_in_time():
    """The controller's --inject: a bad level is refused before anything runs; good ones
    come out in program-time order, each once, without their at_s."""
    from hil.inject.sender import InjectionSender
    from plant.machines import load_machine_set
    machine = load_machine_set(ARROW)
    with pytest.raises(ConfigError, match="growth_pct = 5000"):
        InjectionSender(("friction_growth:growth_pct=5000",), machine)
    sender = InjectionSender(("current_offset:offset_a=0.1,at_s=2",
                              "X/encoder_noise:noise_counts=1,at_s=1"), machine)
    assert sender.due(0.5) == []
    assert sender.due(1.0) == [InjectRequest(0, "encoder_noise", {"noise_counts": 1.0})]
    assert sender.due(5.0) == [InjectRequest(0, "current_offset", {"offset_a": 0.1})]
    assert sender.due(6.0) == [] and len(sender.sent) == 2


def test_counts_an_encoder_lost_stay_lost_when_the_fault_heals():
    """encoder_lost_counts ramped back to 0 leaves the fault terms on (the kernel shows the
    lost counts only while they are): the loss stays until the axis is referenced again."""
    cfg = arrow({"encoder_lost_counts": {"lost_ppm": 100}})
    plant = Plant(cfg)
    inj = Injector(plant.params, cfg, from_machine(cfg))
    inj.update(0.0)
    inj.request("encoder_lost_counts", {"lost_ppm": 0.0}, "test")
    inj.update(1.0)
    assert plant.params[L.P_ENC_LOST] == 0.0 and plant.params[L.P_FAULTS] == 1.0


def test_on_a_machine_of_several_axes_a_flag_names_its_axis():
    """arrow500_xy: Y/... injects into Y only; a flag naming no axis is refused."""
    from hil.inject.schedule import injectors_for
    from plant.machines import load_machine_set
    m = load_machine_set(CONFIGS / "machines" / "arrow500_xy.toml")
    plants = [Plant(c) for c in m.configs]
    x, y = injectors_for(plants, m.configs, m.names, ["Y/preload_loss:loss_pct=20"])
    assert (x.injections, [i.fault for i in y.injections]) == ([], ["preload_loss"])
    with pytest.raises(ConfigError, match="name one: AXIS/FAULT"):
        injectors_for(plants, m.configs, m.names, ["preload_loss:loss_pct=20"])


def test_the_injector_loads_its_kernel_before_the_clock_starts():
    """An injection's start calls plant.effects.faults.faults_active, a numba function:
    building the Injector (before the loop's clock starts) must compile or load it, or
    the first injection stalls the loop for the compile (on a cold cache, seconds: the
    controller's contour monitoring alarmed).  In a fresh process, where nothing else
    has called it."""
    import subprocess
    import sys
    code = ("from plant import Plant; from plant.config import load_machine; "
            "from plant.effects.faults import faults_active as f; "
            "from hil.inject.schedule import Injector; "
            f"cfg = load_machine({str(CONFIGS / 'arrow500_x.toml')!r}); "
            "before = len(f.signatures); Injector(Plant(cfg).params, cfg); "
            "print(before, len(f.signatures))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True)
    assert out.stdout.split() == ["0", "1"]
