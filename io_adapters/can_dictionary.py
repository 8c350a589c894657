"""The live values of one CiA 402 node's objects, other than the master's process data and
the drive's feedback (:mod:`io_adapters.can_node` holds those): the node's own objects
(identity, heartbeat, PDO configuration, the factor group, 6075h/6076h/6502h) and the
drive's, read and written through its :class:`~io_adapters.cia402_objects.ObjectAccess`
and scaled between the drive's increments and the master's position unit.

**Factor group.**  The position unit is set by 608Fh (position encoder resolution:
encoder increments per motor revolution, the drive's: read-only; a linear motor's
"revolution" is one electrical period, two pole pitches), 6091h (gear ratio: motor
revolutions per driving-shaft revolution) and 6092h (feed constant: feed per
driving-shaft revolution).  One position unit is
``608Fh:01 / 608Fh:02 * 6091h:01 / 6091h:02 * 6092h:02 / 6092h:01`` increments
(:attr:`NodeDictionary.factor`); by default 6091h = 1:1 and 6092h = 608Fh, so the unit is
the increment.  A master that writes 6092h:01 = 10000 with 6092h:02 = 1 on a 10 mm lead
speaks in µm.  Speeds are position units per second, accelerations position units per
second squared; the objects of :data:`~io_adapters.cia402_objects.SCALED` units are
converted (rounded to whole units), 6065h = FFFFFFFFh (off) and 607Dh at the type's ends
(off) are not.  6091h and 6092h change in PRE-OPERATIONAL only (0800 0022h otherwise):
the meaning of the process data must not change under a running master.

**Limits.**  A write outside an object's limits (:meth:`NodeDictionary.limits`: the
catalog's, and for 6071h, 60B2h and 6072h the drive's peak current in per mille of 6075h)
is refused with 0609 0031h (too high) or 0609 0032h (too low) before anything else looks
at it; the drive's own checks come after (:class:`~io_adapters.cia402_objects.
ObjectAccessError` with its code).

**1006h and 60C2h.**  The communication cycle period is the drive's object (the machine
file's ``[drive] communication_cycle_s``, by SDO 250-10000 µs in whole drive cycles);
the node keeps a copy (:attr:`NodeDictionary.cycle_s`).  The interpolation time period
60C2h (value * 10^index s) follows 1006h while the two are equal, and starts equal to it.
"""

from io_adapters.can_catalog import (
    ACCELERATION,
    HEARTBEAT_CONSUMER,
    INT_RANGE,
    MODE_BITS,
    MODE_HM,
    MODE_PP,
    MODE_PV,
    PARAMETERS,
    POSITION,
    PRODUCER_HEARTBEAT,
    SDO_ABORT_DEVICE_STATE,
    SDO_ABORT_VALUE_HIGH,
    SDO_ABORT_VALUE_LOW,
    UNSCALED_MARKS,
    VELOCITY,
    spec,
)
from io_adapters.can_pdo import PdoSet
from io_adapters.can_url import CanLink
from io_adapters.cia402_objects import ObjectAccessError
from io_adapters.messages import MODE_CSP, MODE_CST, MODE_CSV, SetpointBounds

#: the cyclic modes a CiA 402 node on this wire runs (the drive's bounds narrow them)
CYCLIC_MODES = frozenset((MODE_CSP, MODE_CSV, MODE_CST))
#: the profile modes: the drive's own trajectories, with the loops CSP needs
PROFILE_MODES = frozenset((MODE_PP, MODE_PV, MODE_HM))
SCALED_KINDS = (POSITION, VELOCITY, ACCELERATION)
PERIOD_INDEXES = (-3, -4, -5, -6)


def offered_modes(bounds: SetpointBounds) -> frozenset:
    """The modes of operation a node offers for a drive that takes ``bounds``: its cyclic
    modes, and with CSP (the drive's position and speed loops) the profile modes too."""
    modes = bounds.modes & CYCLIC_MODES
    return modes | PROFILE_MODES if MODE_CSP in modes else modes


def interpolation_period(cycle_us: int) -> tuple[int, int]:
    """60C2h (value, index) for a period of ``cycle_us``: the coarsest index whose value
    fits UNSIGNED8."""
    for index in PERIOD_INDEXES:
        unit_us = 10 ** (index + 6)
        if cycle_us % unit_us == 0 and cycle_us // unit_us <= 0xFF:
            return cycle_us // unit_us, index
    raise ValueError(f"{cycle_us} µs is no 60C2h period")


class NodeDictionary:
    """One node's object values (see the module docstring).

    Args:
        node_id: the node-ID.
        link: the URL (rated current and torque, the heartbeat consumer at start).
        axis: the axis index of this node's drive.
        owner: the endpoint: its ``objects`` (:class:`~io_adapters.cia402_objects.
            ObjectAccess` or None: the catalog's defaults, stored as written) and
            ``setpoint_bounds``.

    Attributes:
        pdos: the PDO configuration.
        consumer_entry: 1016h:01.
        factor: increments per position unit.
        cycle_s: 1006h, s.
    """

    def __init__(self, node_id: int, link: CanLink, axis: int, owner):
        self.node_id = node_id
        self.axis = axis
        self.owner = owner
        self.rated_ma = link.rated_current_ma
        self.rated_torque_mnm = link.rated_torque_mnm
        self.start_consumer = (0 if link.heartbeat_consumer is None
                               else link.heartbeat_consumer[0] << 16 | link.heartbeat_consumer[1])
        self.pdos = PdoSet(node_id)
        self._modes_of: SetpointBounds | None = None
        self._modes = frozenset()
        self.reset(application=True)

    # -- life cycle --------------------------------------------------------------------
    def reset(self, application: bool) -> None:
        """NMT reset: communication objects back to their start values (and, for a reset
        node, the factor group and the drive's objects, which the drive resets itself)."""
        self.pdos.reset()
        self.consumer_entry = self.start_consumer
        self.producer_ms = 0
        if application:
            self.gear, self.feed = [1, 1], None
            self._stored: dict = {}
        self.refresh()

    def refresh(self) -> None:
        """Take the drive's 1006h and encoder resolution (after a reset, or once the
        drive's objects are attached): the cached cycle, 60C2h equal to it, the factor."""
        self.cycle_s = self._param(0x1006, 0) * 1e-6
        if self.objects is not None:
            value, index = interpolation_period(round(self.cycle_s * 1e6))
            self.objects.write(self.axis, 0x60C2, 1, value)
            self.objects.write(self.axis, 0x60C2, 2, index)
        self._update_factor()

    @property
    def objects(self):
        return self.owner.objects

    def bounds(self) -> SetpointBounds:
        b = self.owner.setpoint_bounds
        return b[self.axis] if self.axis < len(b) else b[0]

    def modes(self) -> frozenset:
        """The modes of operation this node's drive takes (kept for the bounds they were
        found for: every RPDO asks)."""
        bounds = self.bounds()
        if bounds is not self._modes_of:
            self._modes_of, self._modes = bounds, offered_modes(bounds)
        return self._modes

    # -- the factor group ----------------------------------------------------------------
    def _encoder(self) -> tuple[int, int]:
        return self._param(0x608F, 1), self._param(0x608F, 2)

    def _update_factor(self) -> None:
        enc = self._encoder()
        feed = self.feed or list(enc)
        self.factor = enc[0] / enc[1] * self.gear[0] / self.gear[1] * feed[1] / feed[0]

    def to_wire(self, key: tuple[int, int], value: float) -> int:
        """A value of the drive (increments, ...) as the object ``key`` carries it."""
        s = spec(*key)
        if s.unit in SCALED_KINDS and value not in UNSCALED_MARKS.get(key, ()):
            value = value / self.factor
        lo, hi = INT_RANGE[s.data_type]
        return min(max(round(value), lo), hi)

    def from_wire(self, key: tuple[int, int], value: int) -> float:
        """A wire value of ``key`` in the drive's units."""
        s = spec(*key)
        if s.unit in SCALED_KINDS and value not in UNSCALED_MARKS.get(key, ()):
            return value * self.factor
        return value

    # -- reads and writes ----------------------------------------------------------------
    def limits(self, index: int, subindex: int) -> tuple[int | None, int | None]:
        """The (low, high) a write of the object is checked against (None: the type's)."""
        s = spec(index, subindex)
        if (index, subindex) in ((0x6071, 0), (0x60B2, 0), (0x6072, 0)):
            peak = self.bounds().current_a
            if peak != float("inf"):
                top = round(peak * 1e6 / self.rated_ma)
                return (1 if index == 0x6072 else -top), top
        return s.low, s.high

    def check_limits(self, index: int, subindex: int, value: int) -> None:
        low, high = self.limits(index, subindex)
        if high is not None and value > high:
            raise ObjectAccessError(SDO_ABORT_VALUE_HIGH, f"{index:04X}h:{subindex:02X} = "
                                    f"{value} is above {high}")
        if low is not None and value < low:
            raise ObjectAccessError(SDO_ABORT_VALUE_LOW, f"{index:04X}h:{subindex:02X} = "
                                    f"{value} is below {low}")

    def _param(self, index: int, subindex: int) -> int:
        """A drive object in the drive's units (the catalog's default with no drive)."""
        if self.objects is not None:
            return self.objects.read(self.axis, index, subindex)
        return self._stored.get((index, subindex), spec(index, subindex).default)

    def read(self, index: int, subindex: int) -> int | None:
        """The value of an object this dictionary holds (None: the process data, the
        node's read-only constants, which the caller answers)."""
        key = (index, subindex)
        if key in PARAMETERS:
            return self.to_wire(key, self._param(index, subindex))
        owner = self.pdos.owner(index)
        if owner is not None:  # a communication parameter's sub 0 is the catalog's
            return self.pdos.read(index, subindex) if subindex or owner[1] else None
        if key == HEARTBEAT_CONSUMER:
            return self.consumer_entry
        if key == PRODUCER_HEARTBEAT:
            return self.producer_ms
        if index == 0x6091 and subindex:
            return self.gear[subindex - 1]
        if index == 0x6092 and subindex:
            return (self.feed or self._encoder())[subindex - 1]
        if key == (0x6502, 0):
            return sum(MODE_BITS[m] for m in self.modes())
        return None

    def write(self, index: int, subindex: int, value: int, pre_operational: bool) -> None:
        """Write an object this dictionary holds (the caller checked its limits); raises
        :class:`ObjectAccessError` with the abort code to refuse."""
        key = (index, subindex)
        if key in PARAMETERS:
            self._write_param(key, value)
        elif self.pdos.owner(index) is not None:
            self.pdos.write(index, subindex, value, pre_operational)
        elif index in (0x6091, 0x6092):
            if not pre_operational:
                raise ObjectAccessError(SDO_ABORT_DEVICE_STATE, f"{index:04X}h: the factor "
                                        "group changes in PRE-OPERATIONAL only")
            if index == 0x6091:
                self.gear[subindex - 1] = value
            else:
                self.feed = list(self.feed or self._encoder())
                self.feed[subindex - 1] = value
            self._update_factor()
        elif key == HEARTBEAT_CONSUMER:
            self.consumer_entry = value
        elif key == PRODUCER_HEARTBEAT:
            self.producer_ms = value

    def _write_param(self, key: tuple[int, int], value: int) -> None:
        following = key == (0x1006, 0) and self.objects is not None and (
            interpolation_period(round(self.cycle_s * 1e6))
            == (self._param(0x60C2, 1), self._param(0x60C2, 2)))
        drive_value = self.from_wire(key, value)
        if self.objects is None:
            self._stored[key] = drive_value
        else:
            self.objects.write(self.axis, *key, drive_value)
        if key == (0x1006, 0):
            self.cycle_s = self._param(0x1006, 0) * 1e-6
            if following:
                period = interpolation_period(round(self.cycle_s * 1e6))
                self.objects.write(self.axis, 0x60C2, 1, period[0])
                self.objects.write(self.axis, 0x60C2, 2, period[1])
