"""Transports: how a module's frames cross its links (in-process, CAN, serial).

The abstraction is :class:`~dh2rt.transport.base.Transport`; backends are chosen by name
through :func:`~dh2rt.transport.registry.open_transport` and imported only when chosen.
"""

from dh2rt.transport.base import (
    BusEnd,
    FrameFamily,
    Inbound,
    LinkCounters,
    LinkEnd,
    Listening,
    PortEnd,
    Received,
    Transport,
)
from dh2rt.transport.registry import TRANSPORTS, open_transport, parse_spec, transport_class

__all__ = [
    "TRANSPORTS",
    "BusEnd",
    "FrameFamily",
    "Inbound",
    "LinkCounters",
    "LinkEnd",
    "Listening",
    "PortEnd",
    "Received",
    "Transport",
    "open_transport",
    "parse_spec",
    "transport_class",
]
