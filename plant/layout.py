"""Index layout of the flat float64 arrays the axis kernel works on.

Four arrays describe one axis at run time:

``params``
    ``P_COUNT`` scalars (indices ``P_*`` below, SI units) followed by the
    mechanical chains' per-node and per-link arrays, at the offsets stored in
    ``P_OFF_*`` (whole numbers held as float64).
``state``
    ``S_COUNT`` scalars (``S_*``) followed by the chains' node positions,
    velocities and, for the TLM solver, wave variables, at ``P_SOFF_*``.
``inp``
    ``I_COUNT`` setpoints, held constant over one call of the kernel.
``out``
    ``O_COUNT`` signals written at the end of every call.

Module-level integers are compile-time constants for numba, so indexing with
these names costs nothing.  Rotary quantities are in rad, rad/s, N·m; linear
ones in m, m/s, N.  The "motor coordinate" is an angle for rotary motors and a
position for linear motors; the "table coordinate" is a position in m for
screw-driven and linear axes and an angle in rad for direct-drive rotary axes.
"""

# --- model selectors (values of P_MOTOR_MODEL, P_MECH_MODEL, P_SOLVER) ------
MOTOR_DQ = 0  # PMSM in d-q with discrete FOC current PI loops (seed 000)
MOTOR_FIRST_ORDER = 1  # current loop as first-order lag T_cl (seed 004)
MOTOR_COMMUTATION = 2  # torque motor with commutation-angle field weakening (seed 001)

MECH_RIGID = 0  # one inertia (motor, screw and table lumped)
MECH_TWO_MASS = 1  # motor - coupling - load
MECH_SCREW = 2  # motor - coupling - distributed screw - moving nut - table

SOLVER_LUMPED = 0  # semi-implicit (symplectic) Euler on the lumped chains
SOLVER_TLM = 1  # transmission-line modelling for the chains (seed 003)

INPUT_CURRENT = 0  # setpoint is the current (the plant holds the current loop)
INPUT_VOLTAGE = 1  # setpoint is the d-q voltage (the controller holds it)

# --- kernel status codes ----------------------------------------------------
STATUS_OK = 0
STATUS_NONFINITE = 1  # a state became NaN or infinite; the kernel stopped stepping
STATUS_DIVERGED = 2  # |state| exceeded P_DIVERGE_LIMIT; the kernel stopped stepping

# --- scalar parameters --------------------------------------------------------
_p = iter(range(1000))
P_MOTOR_MODEL = next(_p)
P_MECH_MODEL = next(_p)
P_SOLVER = next(_p)
P_DT = next(_p)  # s, integration sub-step
P_SUB_PER_PWM = next(_p)  # sub-steps per PWM / current-controller period
P_DIVERGE_LIMIT = next(_p)  # any |state| above this is a fault

# motor, electrical
P_POLE_PAIRS = next(_p)  # electrical rad per rad (rotary) or per m (linear: pi / pole pitch)
P_R = next(_p)  # ohm, phase resistance
P_LD = next(_p)  # H
P_LQ = next(_p)  # H
P_PSI = next(_p)  # V·s, permanent-magnet flux linkage (dq model)
P_KT = next(_p)  # N·m/A or N/A, torque (force) constant 1.5·p·psi
P_KE = next(_p)  # V·s/rad, back-EMF constant K_S (commutation model)
P_UDC = next(_p)  # V, DC-link voltage (the voltage vector's limit is P_U_MAX)
P_I_MAX = next(_p)  # A, current setpoint limit
P_KP_I = next(_p)  # V/A, current PI proportional gain
P_KI_I = next(_p)  # V/(A·s), current PI integral gain
P_T_CL = next(_p)  # s, first-order current-loop time constant
P_EXP_D = next(_p)  # exp(-R dt / L_d), exact decay over one sub-step
P_EXP_Q = next(_p)  # exp(-R dt / L_q)
P_IQ_KICK_NOW = next(_p)  # 1, first-order model: weight of i_n - target in the sub-step's kick
P_IQ_KICK_NEXT = next(_p)  # 1, that of the next sub-step's kick, less e^(-dt/T) / 2 (pmsm)
P_DECOUPLE = next(_p)  # 1: EMF and cross-coupling precontrol in the d-q current loops
P_FW_ENABLED = next(_p)  # 1: commutation-angle field weakening (seed 001 eq. 6-10)
P_FW_M_MAX = next(_p)  # N·m, rated maximum torque M_max of seed 001 eq. 8

# cogging: up to N_COG harmonics of the electrical angle
N_COG = 6
P_COG_N = next(_p)  # number of harmonics in use
P_COG_ORDER = next(_p)
for _ in range(N_COG - 1):
    next(_p)
P_COG_AMP = next(_p)  # N·m or N
for _ in range(N_COG - 1):
    next(_p)
P_COG_PHASE = next(_p)  # rad
for _ in range(N_COG - 1):
    next(_p)

# transmission
P_LEAD_RATIO = next(_p)  # m/rad, table travel per screw radian (lead / 2 pi); 1 when direct
P_NUT_K = next(_p)  # N/m, nut axial contact stiffness
P_NUT_C = next(_p)  # N·s/m, nut axial damping
P_NUT_GAP = next(_p)  # m, total backlash in the nut (dead zone width)
P_NUT_S0 = next(_p)  # m, nut distance from the screw's first node at table position 0
P_SEG_LEN = next(_p)  # m, length of one screw segment
P_TABLE_M = next(_p)  # kg, table mass (every axis with a table; 0 for rotary tables)
P_EXT_LOAD = next(_p)  # N (N·m for direct rotary), constant external force added to I_LOAD

# ball-screw pitch (lead) error e(u) = sum A sin(k u + phi) + c u, u = nominal table position
N_PITCH = 4
P_PITCH_N = next(_p)  # number of harmonics in use
P_PITCH_WAVENUMBER = next(_p)  # rad/m, 2 pi / period
for _ in range(N_PITCH - 1):
    next(_p)
P_PITCH_AMP = next(_p)  # m
for _ in range(N_PITCH - 1):
    next(_p)
P_PITCH_PHASE = next(_p)  # rad
for _ in range(N_PITCH - 1):
    next(_p)
P_PITCH_LINEAR = next(_p)  # m/m, cumulative lead error c

# table friction (acts on the table, or on the last torsional node reflected)
P_FR_VISCOUS = next(_p)  # N·s/m (N·m·s/rad for direct rotary)
P_FR_COULOMB = next(_p)  # N
P_FR_STATIC = next(_p)  # N, breakaway force F_H
P_FR_STRIBECK_V = next(_p)  # m/s, Stribeck velocity (0: no Stribeck curve)
P_FR_DV = next(_p)  # m/s, Karnopp zero-velocity band half-width
P_FR_VISC_ASYM = next(_p)  # N·s/m: viscous is P_FR_VISCOUS +- this, moving + / moving -
P_FR_REVERSAL_STOP = next(_p)  # 1: a sub-step that would reverse the velocity stops the body
P_PRE_ENABLED = next(_p)  # 1: presliding nonlinear spring (seed 004 eq. 1)
P_PRE_K1 = next(_p)  # N/m, initial presliding stiffness T1 (table units)
P_PRE_X1 = next(_p)  # m, x1
P_PRE_A = next(_p)  # exponent a

# end stops and limit switches of a table with a stroke (screw and linear axes)
P_STROKE = next(_p)  # 1: the table has end stops and limit switches; 0: none (rotary table)
P_STOP_NEG = next(_p)  # m, hard stop at the start of travel (-overtravel)
P_STOP_POS = next(_p)  # m, hard stop at the end of travel (travel + overtravel)
P_STOP_K = next(_p)  # N/m, contact stiffness
P_STOP_C = next(_p)  # N·s/m, contact damping (it only ever pushes the table out)
P_LIMIT_NEG = next(_p)  # m, the negative limit switch is on below this position
P_LIMIT_POS = next(_p)  # m, the positive limit switch is on above this position
P_HOME_SWITCH = next(_p)  # m (rad on rotary tables), the home switch's edge: on below it

# sensors
P_ENC_COUNTS_PER_RAD = next(_p)  # motor encoder counts per motor rad (or per m, linear)
P_SCALE_RES = next(_p)  # m (rad for rotary), linear scale resolution; 0: no scale
P_I_NOISE = next(_p)  # A, standard deviation of current-measurement noise
P_I_LSB = next(_p)  # A, current-measurement quantization step; 0: none
P_SEED = next(_p)  # noise generator seed
N_DELAY_MAX = 32  # longest measurement delay in PWM periods
P_DELAY_N = next(_p)  # measurement delay in whole PWM periods (0: none)
P_INDEX_PERIOD = next(_p)  # rad (m on linear motors) between encoder index marks; 0: 2 pi
P_ENC_ROUND = next(_p)  # 1: encoder and scale counts round to the nearest count; 0: floor
P_ENC_ZERO = next(_p)  # 1: every encoder's grid starts at its reset position (count 0 there)
P_ENC_ORIGIN = next(_p)  # rad (m), motor position of the encoder's count 0 (set at reset)
P_SCALE_ORIGIN = next(_p)  # m (rad), table position of the scale's count 0 (likewise)
P_I_FULL_SCALE = next(_p)  # A, the current ADC clips the measured currents to +-this; 0: never

# chain layout (offsets into params and state; counts)
P_N_ROT = next(_p)  # number of torsional nodes (motor is node 0)
P_N_AX = next(_p)  # number of axial screw nodes (0 without screw)
P_OFF_ROT = next(_p)  # params offset of the torsional chain block
P_OFF_AX = next(_p)  # params offset of the axial chain block
P_SOFF_ROT = next(_p)  # state offset of the torsional chain block
P_SOFF_AX = next(_p)  # state offset of the axial chain block
P_SOFF_DELAY = next(_p)  # state offset of the measurement-delay ring (plant.effects.delay)

# friction on the screw's rotation (plant.effects.screw_friction; issue 14 part 4)
P_SCREW_FRICTION = next(_p)  # 1: any of the four below is set (the kernel skips them otherwise)
P_BRG_COULOMB = next(_p)  # N·m, Coulomb torque of each support bearing
P_NUT_COULOMB = next(_p)  # N·m, Coulomb torque of the nut at no load (its preload torque)
P_NUT_VISCOUS = next(_p)  # N·m·s/rad, viscous torque of the nut on the screw's rotation
P_NUT_LOAD_FR = next(_p)  # 1, Coulomb torque per nut-force torque F lead/2pi

# voltage limit of the current controller (issue 14 part 5)
P_U_MAX = next(_p)  # V, largest d-q voltage vector: U_dc/sqrt(3) SVPWM, U_dc/2 sine PWM
P_U_Q_ONLY = next(_p)  # 1: only |u_q| is limited to P_U_MAX, u_d is not; 0: the d-q vector

# fault terms (issue 14 part 6, plant.effects.faults): 0 after assembly; the run-time
# injector writes them between drive cycles
P_FAULTS = next(_p)  # 1: a term below acts (plant.effects.faults.faults_active); 0: skipped
P_ENC_NOISE = next(_p)  # counts (rms), Gaussian noise on each motor-encoder sample
P_ENC_LOST = next(_p)  # 1, probability that one encoder count is missed, per count travelled
P_I_OFFSET = next(_p)  # A, offset of the phase-a current sensor
P_I_GAIN_ERR = next(_p)  # 1, relative gain error of the phase-a current sensor (0.02: 2 % high)
P_RIPPLE_AMP = next(_p)  # 1, torque ripple as a fraction of the electromagnetic torque
P_RIPPLE_ORDER = next(_p)  # ripple cycles per electrical revolution (may be fractional)
P_RIPPLE_PHASE = next(_p)  # rad, phase of the torque ripple
# holding brake (plant.effects.brake)
P_BRAKE = next(_p)  # N·m (N for linear motors), holding torque on the motor's node; 0: none
P_COUNT = next(_p)
del _p

# A chain of n nodes occupies 6n-3 params (inertias, ground dampers, ground
# springs, link springs, link dampers, link backlash gaps) and 5n-2 state values
# (positions, velocities, a force scratch area, TLM wave variables); the exact
# order is in plant.effects.chain.  With a measurement delay of N PWM periods the
# state ends with a ring of 4 (N+1) values (plant.effects.delay).

# --- scalar state ------------------------------------------------------------
_s = iter(range(1000))
S_TIME = next(_s)  # s
S_SUB_COUNT = next(_s)  # sub-steps since the last current-controller update
S_RNG_COUNTER = next(_s)  # draws made from the noise generator
S_ID = next(_s)  # A (commutation and first-order models use S_IQ only)
S_IQ = next(_s)
S_INT_D = next(_s)  # V, PI integrators
S_INT_Q = next(_s)
S_UD_APPLIED = next(_s)  # V, voltage the inverter applies during this PWM period
S_UQ_APPLIED = next(_s)
S_UD_NEXT = next(_s)  # V, voltage computed this period, applied next (PWM delay)
S_UQ_NEXT = next(_s)
S_ID_MEAS = next(_s)  # A, sampled and held measured currents
S_IQ_MEAS = next(_s)
S_KM = next(_s)  # N·m/A, present torque constant (commutation model)
S_TORQUE = next(_s)  # N·m or N, electromagnetic torque (its kick) of the last sub-step
S_TABLE_X = next(_s)  # table position (screw model; kinematic otherwise)
S_TABLE_V = next(_s)
S_NUT_F = next(_s)  # N, nut force of the last sub-step
S_FRICTION = next(_s)  # N, table friction of the last sub-step
S_STUCK = next(_s)  # 1 while Karnopp stiction holds the friction body
S_PRE_F = next(_s)  # N, presliding friction force
S_PRE_XREV = next(_s)  # m, position at the last reversal
S_PRE_DIR = next(_s)  # +1 / -1, present direction of motion
S_STOP_F = next(_s)  # N, end-stop force on the table of the last sub-step, + toward +x
S_DELAY_HEAD = next(_s)  # ring slot of the newest delayed sample
S_ENC_LOST = next(_s)  # counts, signed: motor-encoder counts lost so far (P_ENC_LOST)
S_ENC_PREV = next(_s)  # counts, true motor-encoder count at the last PWM event (P_ENC_LOST)
S_ENC_NOISE = next(_s)  # counts, encoder noise of the last sample, held until the next
S_IQ_KICK_TAIL = next(_s)  # A, first-order model: the next kick's share from this sub-step's lag
S_COUNT = next(_s)
del _s

# --- inputs ------------------------------------------------------------------
_i = iter(range(100))
I_MODE = next(_i)  # INPUT_CURRENT or INPUT_VOLTAGE
I_ENABLE = next(_i)  # 1: power stage on; 0: torque off (pulses blocked)
I_ID_REF = next(_i)  # A
I_IQ_REF = next(_i)  # A
I_UD = next(_i)  # V (voltage mode)
I_UQ = next(_i)  # V
I_LOAD = next(_i)  # N (N·m for direct rotary), external force on the table
I_BRAKE = next(_i)  # 1: the holding brake holds (P_BRAKE); 0: open
I_COUNT = next(_i)
del _i

# --- outputs -----------------------------------------------------------------
_o = iter(range(100))
O_STATUS = next(_o)
O_TIME = next(_o)  # s
O_MOTOR_POS = next(_o)  # rad (m for linear motors)
O_MOTOR_VEL = next(_o)  # rad/s (m/s)
O_TABLE_POS = next(_o)  # m (rad for direct rotary)
O_TABLE_VEL = next(_o)
# measured signals (encoder, scale, measured currents) lag by [sensors] delay_s; the true
# ones (positions, velocities, currents, torque, forces) never do
O_ENCODER = next(_o)  # motor encoder counts (whole number)
O_SCALE = next(_o)  # linear-scale counts (whole number)
O_ID = next(_o)  # A, true currents
O_IQ = next(_o)
O_ID_MEAS = next(_o)  # A, measured (noise, quantization, sample and hold)
O_IQ_MEAS = next(_o)
O_TORQUE = next(_o)  # N·m (N), electromagnetic torque incl. cogging
O_UD = next(_o)  # V, applied voltages
O_UQ = next(_o)
O_NUT_FORCE = next(_o)  # N
O_FRICTION = next(_o)  # N (N·m), table friction
O_LIMIT_NEG = next(_o)  # 1.0 while the table is beyond the negative limit switch, else 0.0
O_LIMIT_POS = next(_o)  # 1.0 while the table is beyond the positive limit switch, else 0.0
O_END_STOP_F = next(_o)  # N, end-stop force on the table, + pushing toward +x
O_HOME_SWITCH = next(_o)  # 1.0 while the home switch is on, else 0.0 (plant.effects.reference)
O_INDEX = next(_o)  # index marks of the (measured) encoder below its position (whole number)
O_COUNT = next(_o)
del _o
