"""The transports of ``hil bench fuzz``: each a real device endpoint with a raw peer that
sends one frame per drive cycle, and the frame's accounting.

* :class:`UdpLink`: a :class:`~io_adapters.udp.UdpEndpoint` on 127.0.0.1 and a raw UDP
  socket; every datagram is counted once: ``frames`` = datagrams sent = the sum of the
  counters of AdapterStats' identity.
* :class:`SerialLink`: a :class:`~io_adapters.serial_link.SerialEndpoint` on the master
  side of an ``os.openpty`` pair, the raw bytes written to the other side; the identity
  holds after every frame (a byte stream has no frame count of its own: garbage can hold
  candidate frames).
* :class:`RpdoLink` and :class:`SdoLink`: a :class:`~io_adapters.can_cia402.
  CanDriveEndpoint` (node 1, OPERATIONAL, no cycle on its own clock) on python-can's
  ``virtual`` bus with the drive's parameter objects, and a raw bus; after each frame a
  SYNC and the cycle it starts.  An RPDO to the node is counted exactly once: malformed
  (a DLC other than the mapping's), refused (``refused_mode``/``refused_range``) or taken
  (the cycle is heard); any other COB-ID changes none of them.  An SDO download to a
  process-data input is taken (response 60h, the cycle heard) or refused (abort 0609
  0030h, 0031h or 0032h, counted); to any other object it is never a refusal.  At the end
  of each storm of mutations the SDO master resets the node (NMT reset node), as a
  master recovering a drive would: its parameter objects return to the machine file's.
"""

import os
import select
import socket
import time
import uuid
from collections import Counter
from dataclasses import asdict, replace

import can

from hil.bench.fuzz_frames import (
    INPUTS,
    MsgpackFrames,
    RpdoFrames,
    SdoRequests,
    Weather,
    serial_bytes,
)
from hil.drive.objects import DriveObjects
from io_adapters import open_endpoint
from io_adapters.can_dictionary import offered_modes
from io_adapters.serial_link import SerialEndpoint
from io_adapters.udp import UdpEndpoint

#: longest wait for a frame, an answer or a cycle, s
WAIT_S = 5.0
#: the counters of AdapterStats' identity (msgpack transports)
COUNTED = ("received", "malformed", "refused_nonfinite", "refused_mode", "refused_range",
           "duplicates", "out_of_order", "foreign", "stale_session", "handshakes",
           "injections")
CAN_COUNTERS = ("received", "timeouts", "malformed", "refused_mode", "refused_range", "lost")
NODE = 1
SDO_REFUSED = (0x06090030, 0x06090031, 0x06090032)


class FuzzLinkError(RuntimeError):
    """A transport did not deliver within :data:`WAIT_S` (the run cannot go on)."""


def _counted(stats) -> int:
    return sum(getattr(stats, name) for name in COUNTED)


class UdpLink:
    """UDP datagrams of msgpack messages (wire version 1 for one axis, 2 for several)."""

    #: whether the master writes the drive's parameter objects
    WRITES_PARAMETERS = False

    def __init__(self, rng, axes):
        self.endpoint = UdpEndpoint("device", ("127.0.0.1", 0))
        self.endpoint.setpoint_bounds = axes.bounds
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.raw.bind(("127.0.0.1", 0))
        self.frames = MsgpackFrames(rng, axes.limits)
        self.sent = 0

    def feed(self, axes, checks) -> None:
        """Send one message, let the device take it into ``axes.sp``, account for it."""
        data = self.frames.next(axes.controlwords(), axes.counts())
        self.raw.sendto(data, self.endpoint.address)
        self.sent += 1
        if not select.select((self.endpoint,), (), (), WAIT_S)[0]:
            raise FuzzLinkError(f"datagram {self.sent} did not arrive in {WAIT_S} s")
        self.endpoint.recv_setpoint(axes.sp, 0.0)
        stats = self.endpoint.stats
        if not stats.frames == self.sent == _counted(stats):
            checks.fail("counters add up", f"after datagram {self.sent}: {stats}")

    def counters(self) -> dict:
        stats = asdict(self.endpoint.stats)
        return {name: stats[name] for name in ("frames",) + COUNTED}

    def close(self) -> None:
        self.endpoint.close()
        self.raw.close()


class SerialLink:
    """Serial frames of msgpack messages (wire version 1) over a pty pair."""

    WRITES_PARAMETERS = False

    def __init__(self, rng, axes):
        self.rng = rng
        master, self.slave = os.openpty()
        self.endpoint = SerialEndpoint("device", master)  # owns the master side
        self.endpoint.setpoint_bounds = axes.bounds
        self.frames = MsgpackFrames(rng, axes.limits)
        self.framing = Weather(rng)

    def feed(self, axes, checks) -> None:
        payload = self.frames.next(axes.controlwords(), axes.counts())
        os.write(self.slave, serial_bytes(self.rng, payload, self.framing.mutate()))
        if not select.select((self.endpoint,), (), (), WAIT_S)[0]:
            raise FuzzLinkError(f"the bytes written did not arrive in {WAIT_S} s")
        self.endpoint.recv_setpoint(axes.sp, 0.0)
        stats = self.endpoint.stats
        if stats.frames != _counted(stats):
            checks.fail("counters add up", f"{stats}")

    def counters(self) -> dict:
        stats = asdict(self.endpoint.stats)
        return {name: stats[name] for name in ("frames",) + COUNTED + ("bytes_skipped",)}

    def close(self) -> None:
        self.endpoint.close()
        os.close(self.slave)


class _CanLink:
    """A CANopen device endpoint of one axis on a ``virtual`` bus, and the raw bus."""

    WRITES_PARAMETERS = False

    def __init__(self, axes):
        channel = f"hil-fuzz-{uuid.uuid4().hex[:12]}"
        self.rated_ma = round(axes.limits[0].current_a * 1e3)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.endpoint = open_endpoint(f"can://virtual/{channel}?node={NODE}&rated_current_ma="
                                      f"{self.rated_ma}&sync_timeout_ms=60000", "device")
        self.endpoint.objects = DriveObjects(axes.drives.drives, self.endpoint.rated_current_a)
        self.endpoint.setpoint_bounds = axes.bounds
        # a CAN node also takes the profile modes (PP, PV, homing): within its bounds
        axes.bounds = tuple(replace(b, modes=offered_modes(b)) for b in axes.bounds)
        self.frames_sent = 0
        self._send(0x000, bytes([0x01, NODE]))  # NMT start: RPDOs are taken in OPERATIONAL
        deadline = time.monotonic() + WAIT_S
        while self.endpoint.nmt_state != "OPERATIONAL":
            if time.monotonic() > deadline:
                raise FuzzLinkError(f"node {NODE} not OPERATIONAL in {WAIT_S} s")
            time.sleep(0.001)

    def _send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    def _reply(self, cob_id: int, what: str) -> bytes:
        deadline = time.monotonic() + WAIT_S
        while (left := deadline - time.monotonic()) > 0:
            msg = self.bus.recv(left)
            if msg is not None and msg.arbitration_id == cob_id:
                return bytes(msg.data)
        raise FuzzLinkError(f"no {what} in {WAIT_S} s")

    def _cycle(self, into) -> bool:
        """SYNC, then the cycle it starts; whether it was heard."""
        taken = self.endpoint.taken
        self._send(0x080, b"")
        heard = self.endpoint.recv_setpoint(into, WAIT_S)
        if self.endpoint.taken != taken + 1:
            raise FuzzLinkError(f"SYNC {taken + 1} started no cycle in {WAIT_S} s")
        return heard

    def counters(self) -> dict:
        stats = asdict(self.endpoint.stats)
        return {"frames": self.frames_sent, **{name: stats[name] for name in CAN_COUNTERS}}

    def close(self) -> None:
        self.endpoint.close()
        self.bus.shutdown()


class RpdoLink(_CanLink):
    """RPDO frames of any COB-ID, DLC and bytes, mostly the master's own."""

    def __init__(self, rng, axes):
        super().__init__(axes)
        self.frames = RpdoFrames(rng, NODE, axes.limits[0], self.rated_ma / 1e3)
        self.rpdo_sizes = {p.cob_id: p.frame.size for p in self.frames.layouts}

    def feed(self, axes, checks) -> None:
        cob_id, data = self.frames.next(axes.controlwords()[0], axes.counts()[0])
        stats = self.endpoint.stats
        malformed, refused = stats.malformed, stats.refused_mode + stats.refused_range
        self._send(cob_id, data)
        self.frames_sent += 1
        heard = self._cycle(axes.sp)
        new_malformed = stats.malformed - malformed
        new_refused = stats.refused_mode + stats.refused_range - refused
        size = self.rpdo_sizes.get(cob_id)
        if size is None:
            ok = (heard, new_malformed, new_refused) == (False, 0, 0)
        else:
            ok = heard + new_malformed + new_refused == 1 and new_malformed == (len(data) != size)
        if not ok or bool(self.endpoint.refused_axes) != bool(new_refused):
            checks.fail("counters add up", f"frame {self.frames_sent} 0x{cob_id:03X} "
                        f"{data.hex()}: heard {heard}, malformed +{new_malformed}, "
                        f"refused +{new_refused}, refused_axes {self.endpoint.refused_axes}")


class SdoLink(_CanLink):
    """SDO expedited downloads to any object, mostly the master's own process data."""

    WRITES_PARAMETERS = True

    def __init__(self, rng, axes):
        super().__init__(axes)
        self.frames = SdoRequests(rng, NODE, axes.limits[0], self.rated_ma)
        self.answers: Counter = Counter()
        self.resets = 0

    def feed(self, axes, checks) -> None:
        index, sub, request = self.frames.next(axes.controlwords()[0], axes.counts()[0])
        stats = self.endpoint.stats
        refused = stats.refused_mode + stats.refused_range
        self._send(0x600 + NODE, request)
        self.frames_sent += 1
        answer = self._reply(0x580 + NODE, f"SDO answer to {request.hex()}")
        heard = self._cycle(axes.sp)
        new_refused = stats.refused_mode + stats.refused_range - refused
        code = int.from_bytes(answer[4:8], "little") if answer[0] == 0x80 else 0
        self.answers[f"{code:08X}h" if code else "taken"] += 1
        is_input = (index, sub) in INPUTS
        if not (answer[0] in (0x60, 0x80) and answer[1:4] == request[1:4]
                and heard == (is_input and answer[0] == 0x60)
                and new_refused == (is_input and code in SDO_REFUSED)
                and not self.endpoint.refused_axes):  # an SDO abort answers; no fault
            checks.fail("counters add up", f"request {request.hex()}: answer {answer.hex()}, "
                        f"heard {heard}, refused +{new_refused}, "
                        f"refused_axes {self.endpoint.refused_axes}")
        if self.frames.weather.ended_storm:
            self._reset_node()

    def _reset_node(self) -> None:
        """NMT reset node; the boot-up message says it is back (PRE-OPERATIONAL, which
        takes SDO and SYNC)."""
        self._send(0x000, bytes([0x81, NODE]))
        self._reply(0x700 + NODE, "boot-up after the NMT reset")
        self.resets += 1

    def counters(self) -> dict:
        return {**super().counters(), "sdo_answers": dict(sorted(self.answers.items())),
                "nmt_resets": self.resets}


#: decoder name -> (link, number of axes)
LINKS = {"udp-v1": (UdpLink, 1), "udp-v2": (UdpLink, 2), "serial": (SerialLink, 1),
         "can-rpdo": (RpdoLink, 1), "can-sdo": (SdoLink, 1)}
