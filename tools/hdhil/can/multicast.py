"""python-can's ``udp_multicast`` bus limited to its own group.

Every ``udp_multicast`` socket binds the same port on any address, and Linux hands a
socket so bound the datagrams of every group that any socket of the host (of the network
namespace) joined on that port (``IP_MULTICAST_ALL``, on by default). Two buses on two
groups in one namespace would then each receive the other's frames. A rig's buses carry
the same identifiers (the pre-defined connection set numbers each bus alike), so a
process of one of them must receive its own group only: :func:`own_group_only`.
"""

from __future__ import annotations

import socket
from typing import Any

__all__ = ["own_group_only"]

#: Linux's socket options (``<linux/in.h>``, ``<linux/in6.h>``), where :mod:`socket`
#: does not name them.
IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)
IPV6_MULTICAST_ALL = getattr(socket, "IPV6_MULTICAST_ALL", 29)


def own_group_only(bus: Any) -> bool:
    """Make a python-can ``udp_multicast`` bus receive its own group's frames only;
    False (nothing changed) for any other bus, or where the system has no such option."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if not isinstance(sock, socket.socket):
        return False
    try:
        if sock.family == socket.AF_INET:
            sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
        else:
            sock.setsockopt(socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL, 0)
    except OSError:
        return False
    return True
