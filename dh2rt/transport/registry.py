"""A lazy name registry of transports, in the style of python-can's interface table.

Names map to ``"module:Class"`` strings; the module is imported only when its name is
chosen, so ``import dh2rt.transport`` never imports python-can or pyserial.

=============  =====================================================================
``inproc``     in-process bus, no dependencies (:mod:`dh2rt.transport.inproc`)
``virtual``    python-can ``virtual`` bus, one process
``udp``        python-can ``udp_multicast``, across processes (private netns for tests)
``socketcan``  a kernel SocketCAN interface: ``vcan0``, ``can0``, ...
``can``        any python-can interface, named by the ``interface`` option (``slcan``, ``pcan``, ...)
``serial``     one pyserial port per connector, COBS + CRC-16 framing
=============  =====================================================================

A *spec* string (what a ``--transport`` option takes) is a name, ``name:channel``, or a bare
SocketCAN interface name: ``inproc``, ``virtual:robot``, ``udp``, ``udp:239.74.163.2``,
``socketcan:can0``, ``vcan0``, ``serial``.
"""

from __future__ import annotations

import importlib
import re
from typing import Any

from dh2rt.errors import TransportError
from dh2rt.transport.base import Transport
from dh2rt.wire.frame import FrameCodec

TRANSPORTS: dict[str, str] = {
    "inproc": "dh2rt.transport.inproc:InprocTransport",
    "can": "dh2rt.transport.can_bus:CanTransport",
    "virtual": "dh2rt.transport.can_bus:VirtualCanTransport",
    "udp": "dh2rt.transport.can_bus:UdpCanTransport",
    "socketcan": "dh2rt.transport.can_bus:SocketCanTransport",
    "serial": "dh2rt.transport.serial_link:SerialTransport",
}

# Interface names the kernel gives CAN devices: a bare one selects socketcan.
_CAN_IFNAME = re.compile(r"^(v|vx|sl)?can\d+$")


def transport_class(name: str) -> type[Transport]:
    """The class registered as ``name``, imported now."""
    target = TRANSPORTS.get(name)
    if target is None:
        known = ", ".join(sorted(TRANSPORTS))
        raise TransportError(f"unknown transport {name!r}; known transports: {known}")
    module_name, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    if not (isinstance(cls, type) and issubclass(cls, Transport)):
        raise TransportError(f"transport {name!r} points at {target}, which is not a Transport")
    return cls


def parse_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split a transport spec into a registry name and options (``channel``)."""
    spec = spec.strip()
    name, sep, channel = spec.partition(":")
    if name in TRANSPORTS:
        if sep and not channel:
            raise TransportError(f"transport spec {spec!r}: empty channel after ':'")
        if sep and name == "serial":
            raise TransportError("transport spec 'serial' takes no channel: ports are attached per connector")
        return name, ({"channel": channel} if sep else {})
    if not sep and _CAN_IFNAME.match(spec):
        return "socketcan", {"channel": spec}
    known = ", ".join(sorted(TRANSPORTS))
    raise TransportError(
        f"unknown transport {spec!r}; use one of {known}, 'name:channel', or a CAN interface like vcan0"
    )


def open_transport(spec: str, codec: FrameCodec, **options: Any) -> Transport:
    """Open a transport from a name or spec; ``options`` go to the backend's constructor."""
    name, parsed = parse_spec(spec)
    parsed.update(options)
    return transport_class(name)(codec, **parsed)
