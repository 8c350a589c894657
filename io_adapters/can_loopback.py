"""python-can's ``udp_multicast`` bus kept on one interface: the loopback by default.

python-can's bus binds every interface and joins its group on the interface the routing
table picks, so any host on the network can send it frames (an NMT stop included).  This
bus, after python-can has set its socket up, joins the group on one interface address only
(``multicast_if``: 127.0.0.1 or ::1 by default), sends from it, stops the kernel from
handing it the datagrams of groups other sockets joined (``IP_MULTICAST_ALL`` 0), and, on
the loopback, drops every datagram whose sender is not an address of this machine (a
unicast datagram to its port from the network; counted in
:attr:`LoopbackMulticastBus.foreign`).

It does not hear itself, as a CAN controller does not: python-can's bus sends from the
socket it receives on (the group's port, as every other bus on the group does), so each
process receives its own frames back.  This bus sends from a socket of its own, bound to
an ephemeral port of the interface address, and drops the datagrams from that address and
port: in the kernel on IPv4 (a socket filter: they never wake the receive thread, half of
a drive's traffic), and in :meth:`recv` otherwise (counted in
:attr:`LoopbackMulticastBus.own`).

It reaches into python-can 4's ``UdpMulticastBus`` (its ``_multicast`` handler, the
handler's ``_socket`` and ``recv``), which is not public API; tests/test_can_safety.py
checks the behaviour against the installed python-can.
"""

import ctypes
import ipaddress
import socket
import struct
import time

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import pack_message

#: the receive socket's buffer asked for, bytes: about 4000 frames' datagrams (Linux
#: doubles the value asked and caps it at net.core.rmem_max, 4 MiB here; the default
#: 208 KiB holds about 250, a 30 ms stall of the receive thread with two nodes at 1 kHz)
RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024
#: classic BPF (linux/filter.h): attach a socket filter, its instructions, and the
#: offset at which the network (IP) header is reached
SO_ATTACH_FILTER = 26
BPF_LD_H_ABS, BPF_LD_W_ABS, BPF_JEQ_K, BPF_RET_K = 0x28, 0x20, 0x15, 0x06
SKF_NET_OFF = -0x100000
#: Linux's IP_MULTICAST_ALL (linux/in.h); Python's socket module does not name it
IP_MULTICAST_ALL = 49


class LoopbackMulticastBus(UdpMulticastBus):
    """A ``udp_multicast`` bus on one interface (see the module docstring).

    Args:
        channel: the multicast group.
        interface_address: the interface's address: a loopback address keeps the bus on
            the machine; another address puts it on that interface (senders from any
            address are taken then).
        port: the UDP port.

    Attributes:
        foreign: datagrams dropped because their sender was not this machine.
        own: datagrams dropped because this bus sent them.
    """

    def __init__(self, channel: str, interface_address: str, port: int = 43113, **kwargs):
        super().__init__(channel=channel, port=port, **kwargs)
        self.foreign = 0
        self.own = 0
        self._destination = (channel, port)
        address = ipaddress.ip_address(interface_address)
        self._loopback_only = address.is_loopback
        sock = self._multicast._socket
        # every frame on the group comes here, this bus's own included: a receive thread
        # held up for tens of ms must not lose frames (the kernel caps it at rmem_max)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        group = socket.inet_pton(sock.family, channel)
        if sock.family == socket.AF_INET:
            if address.version != 4:
                raise can.CanInitializationError(f"{interface_address} is not an IPv4 "
                                                 f"address for the group {channel}")
            iface = socket.inet_aton(interface_address)
            any_iface = struct.pack("@I", socket.INADDR_ANY)
            try:  # python-can joined on the interface the routing table picked
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_DROP_MEMBERSHIP, group + any_iface)
            except OSError:
                pass  # not joined there after all: nothing to leave
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, group + iface)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
            sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
            self._tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, iface)
            self._tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
        else:
            if not address.is_loopback:
                raise can.CanInitializationError(
                    f"an IPv6 group stays on the loopback (::1) here; {interface_address}: "
                    "use an IPv4 group for another interface, or multicast_if=any")
            index = struct.pack("@I", socket.if_nametoindex("lo"))
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_LEAVE_GROUP,
                            group + struct.pack("@I", 0))
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, group + index)
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, index)
            self._tx = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
            self._tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF, index)
            self._tx.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, 1)
        self._tx.bind((interface_address, 0))
        self._self = self._tx.getsockname()[:2]
        if sock.family == socket.AF_INET:
            _drop_in_kernel(sock, *self._self)
        self._multicast.recv = self._filtered(self._multicast.recv)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to the group from this bus's own socket (never waits: a full
        socket buffer raises, as python-can's bus does)."""
        try:
            self._tx.sendto(pack_message(msg), self._destination)
        except OSError as e:
            raise can.CanOperationError(f"failed to send via socket: {e}") from e

    def shutdown(self) -> None:
        super().shutdown()
        self._tx.close()

    def _filtered(self, recv):
        """``recv`` of python-can's socket handler, dropping this bus's own datagrams and,
        on the loopback, senders from other machines; after a dropped one it reads on
        (within the timeout), so that a poll does not end on a dropped datagram with
        frames queued behind it."""
        local: dict[str, bool] = {}

        def filtered(timeout):
            end = None if timeout is None else time.monotonic() + timeout
            while result := recv(timeout):
                sender = result[1][:2]
                host = sender[0]
                if self._loopback_only and host not in local:
                    local[host] = _is_own_address(host)
                if sender == self._self:
                    self.own += 1
                elif self._loopback_only and not local[host]:
                    self.foreign += 1
                else:
                    return result
                if end is not None:
                    timeout = max(0.0, end - time.monotonic())
            return None
        return filtered


def _drop_in_kernel(sock: socket.socket, address: str, port: int) -> None:
    """A classic BPF socket filter on ``sock`` (IPv4 UDP) that drops the datagrams sent
    from ``address``:``port`` -- this bus's own frames -- before they wake the receive
    thread: half of what a node receives on a SYNC cycle is its own TPDOs.  The filter
    sees the UDP header at offset 0 and the IP header at SKF_NET_OFF."""
    program = [
        (BPF_LD_H_ABS, 0, 0, 0),                     # A = UDP source port
        (BPF_JEQ_K, 0, 3, port),                     # not ours: accept
        (BPF_LD_W_ABS, 0, 0, SKF_NET_OFF + 12),      # A = IPv4 source address
        (BPF_JEQ_K, 0, 1, int(ipaddress.IPv4Address(address))),
        (BPF_RET_K, 0, 0, 0),                        # ours: drop
        (BPF_RET_K, 0, 0, 0xFFFF_FFFF),              # accept the whole datagram
    ]
    code = b"".join(struct.pack("HBBI", c, jt, jf, k & 0xFFFF_FFFF) for c, jt, jf, k in program)
    buffer = ctypes.create_string_buffer(code)
    fprog = struct.pack("HL", len(program), ctypes.addressof(buffer))
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
    except OSError:
        pass  # no socket filters here: recv() drops them (counted in ``own``)


def _is_own_address(host: str) -> bool:
    """``host`` is an address of this machine: a UDP socket can bind it (the kernel picks
    a non-loopback source address for a multicast datagram even when it goes out on lo,
    so a local peer's datagrams do not all come from 127.0.0.1)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((host, 0))
        except OSError:
            return False
    return True
