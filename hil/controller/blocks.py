"""Discrete control blocks run once per cycle: PI, first-order lag, biquad filters.

Coefficients are computed at construction; ``step`` does a few float
operations and allocates nothing.  Every block keeps "compute the output"
and "update the state" in one call because each runs exactly once per cycle.
"""

import math


class PI:
    """Discrete PI controller with output limit and conditional-integration anti-windup.

    u = kp * e + I,  I += kp * T / tn * e  (integrator updated after the output,
    as a drive's PI does; tn = 0 makes it a P controller).  The integrator stops while
    the limit binds and the error pushes further into it; the limit is tested on the
    output alone (:meth:`step`) or on what reaches the limit downstream
    (:meth:`step_within`: SINAMICS freezes the speed controller's I component when the
    torque limit is reached, r1407.5 and .7).
    """

    def __init__(self, kp: float, tn_s: float, period_s: float, limit: float):
        self.kp = kp
        self.ki_t = kp * period_s / tn_s if tn_s > 0.0 else 0.0
        self.limit = limit
        self.integ = 0.0

    def reset(self) -> None:
        """Clear the integrator."""
        self.integ = 0.0

    def finite(self) -> bool:
        """The integrator is finite (x * 0.0 is 0.0 for finite x, NaN otherwise)."""
        return self.integ * 0.0 == 0.0

    def step(self, err: float) -> float:
        """Output for the control error ``err``, limited to ±limit."""
        return self.step_within(err, 0.0)

    def step_within(self, err: float, outer: float) -> float:
        """As :meth:`step`, the integrator stopped by the limit on output + ``outer`` (the
        output's unit: what is added downstream before the limit, D part and
        feed-forward)."""
        u = self.kp * err + self.integ
        total = u + outer
        if total > self.limit:
            if err < 0.0:
                self.integ += self.ki_t * err
            return min(u, self.limit)
        if total < -self.limit:
            if err > 0.0:
                self.integ += self.ki_t * err
            return max(u, -self.limit)
        self.integ += self.ki_t * err
        return u


class ClampPI(PI):
    """PI whose integrator is held within ±limit and always integrates (no conditional
    integration): the integrator itself cannot wind up beyond the limit."""

    def step(self, err: float) -> float:
        """Output for the control error ``err``, limited to ±limit."""
        u = self.kp * err + self.integ
        self.integ = max(-self.limit, min(self.limit, self.integ + self.ki_t * err))
        return max(-self.limit, min(self.limit, u))


class WindupPI(PI):
    """PI without anti-windup: the integrator integrates whatever the output's limit."""

    def step(self, err: float) -> float:
        """Output for the control error ``err``, limited to ±limit."""
        u = self.kp * err + self.integ
        self.integ += self.ki_t * err
        return max(-self.limit, min(self.limit, u))


class PT1:
    """First-order lag with time constant ``tau_s`` (exact for a held input); tau 0 passes."""

    def __init__(self, tau_s: float, period_s: float):
        self.a = math.exp(-period_s / tau_s) if tau_s > 0.0 else 0.0
        self.y = 0.0

    def reset(self, value: float = 0.0) -> None:
        """Set the output (and state) to ``value``."""
        self.y = value

    def finite(self) -> bool:
        """The state is finite."""
        return self.y * 0.0 == 0.0

    def step(self, u: float) -> float:
        """New output for input ``u``."""
        self.y = u + (self.y - u) * self.a
        return self.y


class Delay:
    """A signal delayed by ``n`` calls (a ring of the last n inputs, oldest at ``head``);
    n = 0 passes it unchanged.  Starts (and resets) with zeros in the ring."""

    def __init__(self, n: int):
        self.ring = [0.0] * n
        self.head = 0

    def reset(self) -> None:
        """Fill the ring with zeros."""
        for i in range(len(self.ring)):
            self.ring[i] = 0.0
        self.head = 0

    def step(self, x: float) -> float:
        """The input of ``n`` calls ago (``x`` itself for n = 0); ``x`` goes into the ring."""
        ring = self.ring
        if not ring:
            return x
        out = ring[self.head]
        ring[self.head] = x
        self.head = (self.head + 1) % len(ring)
        return out


class Biquad:
    """Second-order section, transposed direct form II: y = (b0 + b1 z^-1 + b2 z^-2) /
    (1 + a1 z^-1 + a2 z^-2) x.  Build it with :func:`lowpass2` or :func:`notch`;
    the identity section passes the signal unchanged."""

    def __init__(self, b0=1.0, b1=0.0, b2=0.0, a1=0.0, a2=0.0):
        self.b0, self.b1, self.b2, self.a1, self.a2 = b0, b1, b2, a1, a2
        self.z1 = 0.0
        self.z2 = 0.0

    def reset(self) -> None:
        """Clear the delay line."""
        self.z1 = 0.0
        self.z2 = 0.0

    def finite(self) -> bool:
        """The delay line is finite."""
        return self.z1 * 0.0 + self.z2 * 0.0 == 0.0

    def step(self, x: float) -> float:
        """Filter one sample."""
        y = self.b0 * x + self.z1
        self.z1 = self.b1 * x - self.a1 * y + self.z2
        self.z2 = self.b2 * x - self.a2 * y
        return y


def _bilinear(num, den, f0_hz: float, period_s: float) -> Biquad:
    """Bilinear transform of a normalised analogue section (s in units of w0), prewarped
    so that w0 maps exactly."""
    k = 2.0 * math.pi * f0_hz / math.tan(math.pi * f0_hz * period_s)
    w0 = 2.0 * math.pi * f0_hz
    c = k / w0  # s/w0 -> c * (1 - z^-1)/(1 + z^-1)
    n2, n1, n0 = num
    d2, d1, d0 = den
    b0 = n2 * c * c + n1 * c + n0
    b1 = 2.0 * (n0 - n2 * c * c)
    b2 = n2 * c * c - n1 * c + n0
    a0 = d2 * c * c + d1 * c + d0
    a1 = 2.0 * (d0 - d2 * c * c)
    a2 = d2 * c * c - d1 * c + d0
    return Biquad(b0 / a0, b1 / a0, b2 / a0, a1 / a0, a2 / a0)


def lowpass2(f_hz: float, damping: float, period_s: float) -> Biquad:
    """PT2 low-pass 1 / ((s/w0)^2 + 2 D s/w0 + 1); f_hz <= 0 gives the identity."""
    if f_hz <= 0.0:
        return Biquad()
    return _bilinear((0.0, 0.0, 1.0), (1.0, 2.0 * damping, 1.0), f_hz, period_s)


def notch(f_hz: float, bandwidth_hz: float, depth_db: float, period_s: float) -> Biquad:
    """Notch ((s/w0)^2 + 2 D_z s/w0 + 1) / ((s/w0)^2 + 2 D_p s/w0 + 1) with D_p = B / (2 f0)
    (B the -3 dB width) and D_z = D_p * 10^(depth/20); f_hz <= 0 gives the identity."""
    if f_hz <= 0.0:
        return Biquad()
    dp = bandwidth_hz / (2.0 * f_hz)
    dz = dp * 10.0 ** (depth_db / 20.0)
    return _bilinear((1.0, 2.0 * dz, 1.0), (1.0, 2.0 * dp, 1.0), f_hz, period_s)
