"""Which connectors of the loop's modules are docked, and the link end each one attaches:
a CAN link id and side on a bus, or one pty end of the link emulator on serial links."""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass

from dh2rt.docking import End
from dh2rt.transport.base import BusEnd, LinkEnd, PortEnd
from hil.link_emulator import LinkEmulator


@dataclass(slots=True)
class WorldLink:
    """One docked connector pair: ``a.a_conn`` is side 0, ``b.b_conn`` side 1."""

    link_id: int
    a: int
    a_conn: int
    b: int
    b_conn: int


class LinkMap:
    """The docked links, by id and by either end."""

    def __init__(self, emulator: LinkEmulator | None = None, ports: Mapping[End, PortEnd] | None = None) -> None:
        self.emulator = emulator
        #: real serial ports per (module, connector) (a hardware map): no emulator link then
        self.ports = dict(ports or {})
        self.links: dict[int, WorldLink] = {}
        self.peer: dict[End, WorldLink] = {}
        self._ids = itertools.count()

    def add(self, a: int, a_conn: int, b: int, b_conn: int) -> WorldLink:
        link = WorldLink(next(self._ids), a, a_conn, b, b_conn)
        if self.emulator is not None:
            self.emulator.add_link(link.link_id)
        self.links[link.link_id] = link
        self.peer[(a, a_conn)] = link
        self.peer[(b, b_conn)] = link
        return link

    def remove(self, link: WorldLink) -> None:
        """Forget the link (an undocked emulator link stays open, relaying nothing)."""
        del self.peer[(link.a, link.a_conn)]
        del self.peer[(link.b, link.b_conn)]
        if self.emulator is not None:
            self.emulator.undock(link.link_id)

    def peer_of(self, end: End) -> End | None:
        """The module and connector docked at ``end``, if any."""
        link = self.peer.get(end)
        if link is None:
            return None
        return (link.b, link.b_conn) if end == (link.a, link.a_conn) else (link.a, link.a_conn)

    def end(self, link: WorldLink, module: int, connector: int) -> LinkEnd:
        """The link end ``module`` attaches at ``connector``: side 0 is the link's ``a``."""
        side = 0 if (module, connector) == (link.a, link.a_conn) else 1
        if (module, connector) in self.ports:
            return self.ports[(module, connector)]
        if self.emulator is not None:
            return PortEnd(self.emulator.link(link.link_id).paths[side])
        return BusEnd(link.link_id, side)

    def attachments(self, module: int) -> dict[int, LinkEnd]:
        """Connector -> link end of every docked connector of ``module``."""
        return {c: self.end(link, m, c) for (m, c), link in sorted(self.peer.items()) if m == module}
