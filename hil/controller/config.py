"""The ``[controller]`` section of a machine file: the simulated NC's machine data.

Keys follow SINUMERIK/SINAMICS parameters where one exists (named in the
doc); values are in the units their names carry.  For rotary axes the
velocity, acceleration and jerk keys take degrees (``_deg_min``,
``_deg_s2``, ``_deg_s3``) and K_v reads (1000 deg/min)/deg, as MD32200 does.
Cycle times are whole multiples of the plant's PWM period (the basic clock).

The axis monitoring (:mod:`hil.controller.monitoring`, alarms in
:mod:`hil.controller.alarms`) takes its tolerances from the MDs of SINUMERIK's axis
monitoring with their defaults: contour MD36400 (1 mm), standstill MD36030 (0.2 mm) after
MD36040 (0.4 s), clamping MD36050 (0.5 mm); an alarm's braking ends at MD36060 (5 mm/min)
or after MD36620 (0.1 s).  Rotary axes take them in deg and deg/min.  The clamp and
unclamp M functions (M10, M11 by default) are the machine's own (its PLC clamps the
axis), so they are machine data here.
"""

import math
from dataclasses import dataclass

from hil.controller.program import ClampCodes
from plant.config import MachineConfig, build_section, check_applies
from plant.errors import ConfigError
from plant.schema import key

LINEAR_KINDS = "kind=screw|linear"
#: M functions with a meaning of their own in SINUMERIK (program stop and end, spindle, tool
#: change, subprogram end, spindle positioning, gear stages, spindle to axis mode): not
#: available as clamp M functions
RESERVED_M_CODES = frozenset((0, 1, 2, 3, 4, 5, 6, 17, 19, 30, 40, 41, 42, 43, 44, 45, 70))
#: the speed integrator's anti-windup (``speed_antiwindup``)
ANTIWINDUP_MODES = ("conditional", "torque_setpoint", "clamp", "none")
#: ``speed_integrator_stop`` moved into ``speed_antiwindup``: its values there
INTEGRATOR_STOP_MOVED = {"pi_output": "conditional", "torque_setpoint": "torque_setpoint"}


@dataclass(frozen=True, kw_only=True)
class ControllerSection:
    """Controller and drive-control settings."""
    plant_input: str = key("-", "What the controller sends: 'current' (the plant's drive holds "
                           "the current loop) or 'voltage' (the controller's current loop "
                           "sends d-q voltages).", "current", choices=("current", "voltage"))
    speed_cycle_ratio: int = key("1", "Speed-loop cycle in PWM periods.", 1, ge=1, le=64)
    position_cycle_ratio: int = key("1", "Position-loop cycle in PWM periods (a multiple of "
                                    "the speed cycle).", 16, ge=1, le=256)
    ipo_cycle_ratio: int = key("1", "Interpolation (IPO) cycle in PWM periods (a multiple of "
                               "the position cycle).", 32, ge=1, le=1024)
    feedback: str = key("-", "Position-loop measuring system: 'scale' (direct, linear scale) "
                        "or 'motor' (motor encoder through the lead).", "motor",
                        choices=("scale", "motor"))
    kv_m_min_per_mm: float = key("(m/min)/mm", "Position-loop gain K_v (MD32200): 1 gives 1 mm "
                                 "following error at 1 m/min.", gt=0.0, le=100.0)
    speed_ff: bool = key("-", "Speed feed-forward (MD32620).", True)
    speed_ff_weight: float = key("1", "Weight of the speed feed-forward (MD32610).", 1.0,
                                 ge=0.0, le=2.0)
    torque_ff: bool = key("-", "Torque (acceleration) feed-forward from the interpolator's "
                          "acceleration and the axis inertia.", False)
    feedforward_interpolation: str = key("-", "Speed feed-forward between position cycles: "
                                         "'hold' (held per position cycle) or 'linear' "
                                         "(interpolated at every speed cycle towards the next "
                                         "position cycle's value, a fine interpolation; the "
                                         "P part is held).", "hold",
                                         choices=("hold", "linear"))
    speed_actual_filter_s: float = key("s", "Time constant of the first-order filter on the "
                                       "measured motor speed the speed loop uses (p1441 "
                                       "class, exact for a held input); 0: none.", 0.0,
                                       ge=0.0, le=1.0)
    speed_antiwindup: str = key("-", "Anti-windup of the speed integrator at the current "
                                "limit: 'conditional' (no integration that drives the PI's "
                                "own output further into the limit K_t I_max), "
                                "'torque_setpoint' (the same on the whole torque setpoint, "
                                "PI + D + feed-forward, as SINAMICS freezes the I component "
                                "at the torque limit, r1407.5/.7), 'clamp' (the integrator "
                                "itself held within the limit, always integrating) or "
                                "'none'.", "conditional",
                                choices=ANTIWINDUP_MODES)
    current_delay_cycles: int = key("1", "Computation delay of the current setpoint in PWM "
                                    "periods: the drive applies the speed loop's output this "
                                    "many periods later.", 0, ge=0, le=64)
    speedctrl_equiv_time_s: float = key("s", "Equivalent time constant of the closed speed "
                                        "loop (MD32810); delays the position setpoint of the P "
                                        "path when feed-forward is on.", 0.0, ge=0.0, le=1.0)
    speed_kp_nms_per_rad: float = key("N*m*s/rad", "Speed-controller gain (p1460).", 0.0,
                                      ge=0.0, le=1e4, only="kind=screw|rotary")
    speed_kp_ns_per_m: float = key("N*s/m", "Speed-controller gain of a linear motor.", 0.0,
                                   ge=0.0, le=1e7, only="kind=linear")
    speed_tn_s: float = key("s", "Speed-controller integral time (p1462); 0: P only.", 0.0,
                            ge=0.0, le=10.0)
    speed_kd_nms2_per_rad: float = key("N*m*s^2/rad", "Speed-controller D gain (seed 003 eq. "
                                       "7).", 0.0, ge=0.0, le=10.0, only="kind=screw|rotary")
    speed_kd_ns2_per_m: float = key("N*s^2/m", "Speed-controller D gain of a linear motor.",
                                    0.0, ge=0.0, le=1e4, only="kind=linear")
    speed_setpoint_lowpass_hz: float = key("Hz", "PT2 low-pass on the speed setpoint (p1416 "
                                           "class); 0: off.", 0.0, ge=0.0, le=1e5)
    current_setpoint_lowpass_hz: float = key("Hz", "PT2 low-pass on the current setpoint "
                                             "(p1658 class); 0: off.", 0.0, ge=0.0, le=1e5)
    notch_hz: float = key("Hz", "Notch on the current setpoint (p1663 class); 0: off.", 0.0,
                          ge=0.0, le=1e5)
    notch_bandwidth_hz: float = key("Hz", "-3 dB width of the notch.", 0.0, ge=0.0, le=1e5)
    notch_depth_db: float = key("dB", "Notch depth (negative dB; -inf dB is not allowed).",
                                -40.0, ge=-200.0, le=0.0)
    max_velocity_mm_min: float = key("mm/min", "Maximum axis velocity (MD32000); G0 feed.",
                                     0.0, ge=0.0, le=1e6, only=LINEAR_KINDS)
    max_acceleration_m_s2: float = key("m/s^2", "Maximum acceleration (MD32300).", 0.0,
                                       ge=0.0, le=1000.0, only=LINEAR_KINDS)
    max_jerk_m_s3: float = key("m/s^3", "Maximum jerk (MD32431); 0: no jerk limit.", 0.0,
                               ge=0.0, le=1e6, only=LINEAR_KINDS)
    max_velocity_deg_min: float = key("deg/min", "Maximum axis velocity (MD32000).", 0.0,
                                      ge=0.0, le=1e7, only="kind=rotary")
    max_acceleration_deg_s2: float = key("deg/s^2", "Maximum acceleration (MD32300).", 0.0,
                                         ge=0.0, le=1e7, only="kind=rotary")
    max_jerk_deg_s3: float = key("deg/s^3", "Maximum jerk (MD32431); 0: no jerk limit.", 0.0,
                                 ge=0.0, le=1e9, only="kind=rotary")
    current_kp_v_per_a: float = key("V/A", "Current PI gain (plant_input = 'voltage').", 0.0,
                                    ge=0.0, le=1e4)
    current_ti_s: float = key("s", "Current PI integral time (plant_input = 'voltage').", 0.0,
                              ge=0.0, le=10.0)
    encoder_feedback_polarity: int = key("1", "Sign of the position actual value (MD32110 "
                                         "ENC_FEEDBACK_POL): -1 reverses it; 0 or 1 do not.",
                                         1, ge=-1, le=1)
    contour_tol_mm: float = key("mm", "Contour monitoring (MD36400 CONTOUR_TOL): largest "
                                "deviation of the actual position from the one the loop "
                                "model expects; beyond it alarm 25050.", 1.0, gt=0.0, le=1000.0,
                                only=LINEAR_KINDS)
    contour_tol_deg: float = key("deg", "Contour monitoring tolerance of a rotary axis "
                                 "(MD36400).", 1.0, gt=0.0, le=360.0, only="kind=rotary")
    standstill_pos_tol_mm: float = key("mm", "Standstill monitoring (MD36030 "
                                       "STANDSTILL_POS_TOL): largest following error while "
                                       "the axis is meant to stand still; beyond it alarm "
                                       "25040.", 0.2, gt=0.0, le=1000.0, only=LINEAR_KINDS)
    standstill_pos_tol_deg: float = key("deg", "Standstill tolerance of a rotary axis "
                                        "(MD36030).", 0.2, gt=0.0, le=360.0, only="kind=rotary")
    standstill_delay_time_s: float = key("s", "Standstill monitoring delay (MD36040 "
                                         "STANDSTILL_DELAY_TIME): from the end of a motion to "
                                         "the start of standstill monitoring.", 0.4, ge=0.0,
                                         le=100.0)
    clamp_pos_tol_mm: float = key("mm", "Clamping monitoring (MD36050 CLAMP_POS_TOL): how far "
                                  "a clamped axis may move from where it was clamped; beyond "
                                  "it alarm 26000.", 0.5, gt=0.0, le=1000.0, only=LINEAR_KINDS)
    clamp_pos_tol_deg: float = key("deg", "Clamping tolerance of a rotary axis (MD36050).",
                                   0.5, gt=0.0, le=360.0, only="kind=rotary")
    standstill_velo_tol_mm_min: float = key("mm/min", "Axis stationary below this speed "
                                            "(MD36060 STANDSTILL_VELO_TOL): ends the braking "
                                            "of an alarm.", 5.0, gt=0.0, le=1e5, only=LINEAR_KINDS)
    standstill_velo_tol_deg_min: float = key("deg/min", "Axis stationary speed of a rotary "
                                             "axis (MD36060).", 5.0, gt=0.0, le=1e6,
                                             only="kind=rotary")
    servo_disable_delay_time_s: float = key("s", "Longest braking after an alarm before the "
                                            "drive is disabled anyway (MD36620 "
                                            "SERVO_DISABLE_DELAY_TIME).", 0.1, ge=0.0, le=100.0)
    clamp_m_code: int = key("1", "M function that clamps the axis (a PLC M function of the "
                            "machine; SINUMERIK has no MD for it): clamping monitoring "
                            "replaces standstill monitoring until the unclamp M function.",
                            ClampCodes().clamp, ge=0, le=99999)
    unclamp_m_code: int = key("1", "M function that releases the clamp.", ClampCodes().unclamp,
                              ge=0, le=99999)


@dataclass(frozen=True)
class AxisLimits:
    """Interpolator limits in SI (m or rad): velocity /s, acceleration /s², jerk /s³ (0: none)."""
    velocity: float
    acceleration: float
    jerk: float


@dataclass(frozen=True)
class MonitoringLimits:
    """The axis monitoring's machine data in SI units of the table coordinate.

    Attributes:
        contour_tol: MD36400, m (rad on rotary axes).
        standstill_tol: MD36030, m (rad).
        standstill_delay_s: MD36040, s.
        clamp_tol: MD36050, m (rad).
        standstill_velocity: MD36060, m/s (rad/s).
        disable_delay_s: MD36620, s.
    """
    contour_tol: float
    standstill_tol: float
    standstill_delay_s: float
    clamp_tol: float
    standstill_velocity: float
    disable_delay_s: float


def motor_constant(cfg: MachineConfig) -> float:
    """The motor's torque per q-current, N·m/A (force per current, N/A, for linear motors)."""
    mo = cfg.motor
    linear = cfg.machine.kind == "linear"
    return mo.force_constant_n_per_a if linear else mo.torque_constant_nm_per_a


def cnc_unit(cfg: MachineConfig) -> tuple[float, str]:
    """Factor from SI table units (m, rad) to the CNC's (mm, deg), and that unit."""
    return (180.0 / math.pi, "deg") if cfg.machine.kind == "rotary" else (1e3, "mm")


def monitoring_limits(cfg: MachineConfig, section: ControllerSection) -> MonitoringLimits:
    """The monitoring machine data of ``section`` in SI (the keys for the axis's kind)."""
    k, unit = cnc_unit(cfg)

    def si(name: str) -> float:
        return getattr(section, f"{name}_{unit}") / k

    return MonitoringLimits(
        contour_tol=si("contour_tol"), standstill_tol=si("standstill_pos_tol"),
        standstill_delay_s=section.standstill_delay_time_s, clamp_tol=si("clamp_pos_tol"),
        standstill_velocity=getattr(section, f"standstill_velo_tol_{unit}_min") / k / 60.0,
        disable_delay_s=section.servo_disable_delay_time_s)


def clamp_codes(section: ControllerSection) -> ClampCodes:
    """The axis's clamp and unclamp M functions, for the program parser."""
    return ClampCodes(section.clamp_m_code, section.unclamp_m_code)


def kv_si(section: ControllerSection) -> float:
    """K_v in 1/s: (m/min)/mm -> (m/s)/m is a factor 1000/60."""
    return section.kv_m_min_per_mm * 1000.0 / 60.0


def axis_limits(cfg: MachineConfig, section: ControllerSection) -> AxisLimits:
    """The interpolator's limits in SI units of the table coordinate."""
    if cfg.machine.kind == "rotary":
        d = math.pi / 180.0
        return AxisLimits(section.max_velocity_deg_min * d / 60.0,
                          section.max_acceleration_deg_s2 * d, section.max_jerk_deg_s3 * d)
    return AxisLimits(section.max_velocity_mm_min / 60000.0, section.max_acceleration_m_s2,
                      section.max_jerk_m_s3)


def _refuse_moved_key(cfg: MachineConfig, raw: dict) -> None:
    """ConfigError for a key that moved, naming the key and value to write instead (a
    silent alias would leave two spellings of one setting in the machine files)."""
    if "speed_integrator_stop" in raw:
        old = raw["speed_integrator_stop"]
        new = INTEGRATOR_STOP_MOVED.get(old) if isinstance(old, str) else None
        instead = (f"speed_antiwindup = {new!r}" if new else "speed_antiwindup, one of "
                   + ", ".join(map(repr, ANTIWINDUP_MODES)))
        raise ConfigError(f"{cfg.path}: [controller] speed_integrator_stop = {old!r}: the key "
                          f"has moved; write {instead}")


def load_controller(cfg: MachineConfig) -> ControllerSection:
    """Check the machine file's ``[controller]`` section; ConfigError names file and key."""
    raw = cfg.section("controller")
    if not raw:
        raise ConfigError(f"{cfg.path}: section [controller] is missing (the simulated "
                          "controller needs its machine data)")
    _refuse_moved_key(cfg, raw)
    sec = build_section(ControllerSection, raw, cfg.path, "controller")
    check_applies(sec, raw, {"kind": cfg.machine.kind, "model": cfg.motor.model}, cfg.path,
                "controller")
    kp = sec.speed_kp_ns_per_m if cfg.machine.kind == "linear" else sec.speed_kp_nms_per_rad
    if kp <= 0.0:
        name = "speed_kp_ns_per_m" if cfg.machine.kind == "linear" else "speed_kp_nms_per_rad"
        raise ConfigError(f"{cfg.path}: [controller] {name} must be given and > 0")
    lim = axis_limits(cfg, sec)
    unit = "deg" if cfg.machine.kind == "rotary" else "mm"
    if lim.velocity <= 0.0 or lim.acceleration <= 0.0:
        raise ConfigError(f"{cfg.path}: [controller] the maximum velocity and acceleration "
                          f"(max_velocity_{unit}_min, max_acceleration_*) must be > 0")
    if sec.position_cycle_ratio % sec.speed_cycle_ratio:
        raise ConfigError(f"{cfg.path}: [controller] position_cycle_ratio = "
                          f"{sec.position_cycle_ratio} must be a multiple of speed_cycle_ratio "
                          f"= {sec.speed_cycle_ratio}")
    if sec.ipo_cycle_ratio % sec.position_cycle_ratio:
        raise ConfigError(f"{cfg.path}: [controller] ipo_cycle_ratio = {sec.ipo_cycle_ratio} "
                          f"must be a multiple of position_cycle_ratio = "
                          f"{sec.position_cycle_ratio}")
    if sec.plant_input == "voltage":
        if cfg.motor.model != "dq":
            raise ConfigError(f"{cfg.path}: [controller] plant_input = 'voltage' needs "
                              "motor.model = 'dq'")
        if sec.current_kp_v_per_a <= 0.0 or sec.current_ti_s <= 0.0:
            raise ConfigError(f"{cfg.path}: [controller] current_kp_v_per_a (V/A) and "
                              "current_ti_s (s) must be > 0 when plant_input = 'voltage'")
    if sec.feedback == "scale" and (cfg.machine.kind == "rotary"
                                    or cfg.sensors.scale_resolution_m <= 0.0):
        raise ConfigError(f"{cfg.path}: [controller] feedback = 'scale' needs [sensors] "
                          "scale_resolution_m > 0 m")
    for name in ("clamp_m_code", "unclamp_m_code"):
        code = getattr(sec, name)
        if code in RESERVED_M_CODES:
            raise ConfigError(f"{cfg.path}: [controller] {name} = {code}: M{code} has a "
                              "meaning of its own; reserved are M"
                              + ", M".join(str(c) for c in sorted(RESERVED_M_CODES)))
    if sec.clamp_m_code == sec.unclamp_m_code:
        raise ConfigError(f"{cfg.path}: [controller] unclamp_m_code = {sec.unclamp_m_code} is "
                          "clamp_m_code too: clamping and unclamping need two M functions")
    if sec.notch_hz > 0.0 and sec.notch_bandwidth_hz <= 0.0:
        raise ConfigError(f"{cfg.path}: [controller] notch_bandwidth_hz must be > 0 Hz when "
                          "notch_hz is set")
    return sec
