"""A module's links on a shared bus, negotiated with its neighbours: the I/O around the sans-IO
:class:`~dh2rt.negotiation.LinkNegotiator`.

Each cycle (and, before the first, every period until the contacts made at power-up are
linked) :meth:`NegotiatedLinks.step` hands the negotiator what happened since the last step,
in order: the connector-local channels' events (contact made or lost, a few bytes from the
touching connector), then the bus's management frames, then the time; it carries out each
action before the next input: bytes to a channel, a management frame to the bus, a link end
attached to or detached from the module's runtime. Nothing here names a module: the
negotiator's nonces live one negotiation long, and its randomness comes from the system.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterable
from typing import Any

from dh2rt.closing import Closing
from dh2rt.negotiation import Attach, Detach, LinkNegotiator, SendBus, SendLocal
from dh2rt.transport.base import FrameFamily, Inbound, LinkEnd
from drivers.connector_channel import CONTACT, LOST, ConnectorChannels


class NegotiatedLinks(Closing):
    """Drives one module's link negotiation (see the module docs).

    ``transport`` is the module's CAN transport: this is its management frames' handler,
    and keeps what the transport's polls hand it until the next :meth:`step` (the negotiator
    takes them after the channels' events, in the order they came); ``attach`` and ``detach``
    are the runtime's, so links come and go as Hellos and liveness expect. ``log`` takes one
    line per link made or given up."""

    def __init__(
        self,
        channels: ConnectorChannels,
        transport: Any,
        connectors: Iterable[int],
        now: float,
        attach: Callable[[int, LinkEnd], None],
        detach: Callable[[int], None],
        log: Callable[[str], None],
    ) -> None:
        self.channels = channels
        self.transport = transport
        self.negotiator = LinkNegotiator(tuple(connectors), random.Random(), now=now)
        self._attach, self._detach, self._log = attach, detach, log
        self._bus_frames: list[bytes] = []
        self._listening = transport.listen(FrameFamily.MANAGEMENT, self._bus_received)

    def _bus_received(self, frame: Inbound) -> None:
        self._bus_frames.append(frame.payload)

    @property
    def settled(self) -> bool:
        """Every connector in contact has its link."""
        linked = self.negotiator.links
        return all(c in linked for c, touching in self.channels.contacts().items() if touching)

    def step(self, now: float) -> None:
        neg = self.negotiator
        for connector, event in self.channels.poll(now):
            if event == CONTACT:
                self._do(neg.contact(connector, True))
            elif event == LOST:
                self._do(neg.contact(connector, False))
            elif isinstance(event, bytes):
                self._do(neg.local_received(connector, event))
        frames, self._bus_frames = self._bus_frames, []
        for data in frames:
            self._do(neg.bus_received(data))
        self._do(neg.tick(now))

    def _do(self, actions: Iterable[object]) -> None:
        for action in actions:
            if isinstance(action, SendLocal):
                self.channels.send(action.connector, action.data)
            elif isinstance(action, SendBus):
                self.transport.send_management(action.frame.arbitration_id, action.frame.data)
            elif isinstance(action, Attach):
                self._log(
                    f"link negotiated: connector {action.connector} is link {action.end.link_id} side {action.end.side}"
                )
                self._attach(action.connector, action.end)
            elif isinstance(action, Detach):
                self._log(f"link given up: connector {action.connector}")
                self._detach(action.connector)

    def close(self) -> None:
        """Release every link on the bus (a clean stop), then close the channels and stop
        taking the bus's management frames."""
        try:
            self._do(self.negotiator.shutdown())
        finally:
            self._listening.close()
            self.channels.close()
