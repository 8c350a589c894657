"""python-can's ``udp_multicast`` bus kept on one interface: the loopback by default.

python-can's bus binds every interface and joins its group on the interface the routing
table picks, so any host on the network can send it frames (an NMT stop included).  This
bus, after python-can has set its socket up, joins the group on one interface address only
(``multicast_if``: 127.0.0.1 or ::1 by default), sends from it, stops the kernel from
handing it the datagrams of groups other sockets joined (``IP_MULTICAST_ALL`` 0), and, on
the loopback, drops every datagram whose sender is not an address of this machine (a
unicast datagram to its port from the network; counted in
:attr:`LoopbackMulticastBus.foreign`).

It reaches into python-can 4's ``UdpMulticastBus`` (its ``_multicast`` handler, the
handler's ``_socket`` and ``recv``), which is not public API; tests/test_can_safety.py
checks the behaviour against the installed python-can.
"""

import ipaddress
import socket
import struct

import can
from can.interfaces.udp_multicast import UdpMulticastBus

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
    """

    def __init__(self, channel: str, interface_address: str, port: int = 43113, **kwargs):
        super().__init__(channel=channel, port=port, **kwargs)
        self.foreign = 0
        address = ipaddress.ip_address(interface_address)
        self._loopback_only = address.is_loopback
        sock = self._multicast._socket
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
        if self._loopback_only:
            self._multicast.recv = self._from_loopback(self._multicast.recv)

    def _from_loopback(self, recv):
        """``recv`` of python-can's socket handler, dropping senders from other machines."""
        local: dict[str, bool] = {}

        def filtered(timeout):
            result = recv(timeout)
            if result:
                host = result[1][0]
                if host not in local:
                    local[host] = _is_own_address(host)
                if not local[host]:
                    self.foreign += 1
                    return None
            return result
        return filtered


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
