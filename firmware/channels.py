"""The connector-local channels a module's config names (firmware.config.ChannelSpec), opened for
:class:`firmware.negotiated_links.NegotiatedLinks`: the HIL world's emulation, or a UART and a
GPIO contact pin per connector."""

from __future__ import annotations

from collections.abc import Mapping

from drivers.connector_channel import ConnectorChannel, ConnectorChannels
from firmware.config import ChannelSpec


def open_channels(specs: Mapping[int, ChannelSpec]) -> ConnectorChannels:
    """The module's connector-local channels: the HIL world's emulation (a pty each), or a
    UART and a GPIO contact pin per connector."""
    emulated = {c: s.device for c, s in specs.items() if s.contact is None}
    hardware = {c: s for c, s in specs.items() if s.contact is not None}
    if not hardware:
        return ConnectorChannels.open_emulated(emulated)
    from drivers.connector_channel import ContactPin, PtyConnectorChannel, UartGpioConnectorChannel

    channels: dict[int, ConnectorChannel] = {}
    try:
        for c, path in emulated.items():
            channels[c] = PtyConnectorChannel(path)
        for c, spec in hardware.items():
            assert spec.contact is not None
            pin = ContactPin(spec.contact, active_low=spec.active_low)
            channels[c] = UartGpioConnectorChannel(spec.device, pin, baudrate=spec.baud)
    except BaseException:
        for channel in channels.values():
            channel.close()
        raise
    return ConnectorChannels(channels)
