"""The transport contract on every backend this machine can run (udp: test_contract_udp.py)."""

from __future__ import annotations

import pytest

from dh2rt.testing import CanHarness, InprocHarness, TransportContract, TransportHarness
from dh2rt.transport.base import PortEnd, Transport
from dh2rt.transport.can_bus import socketcan_problem
from dh2rt.transport.serial_link import SerialTransport
from hil.link_emulator import LinkEmulator


class SerialHarness(TransportHarness):
    """Real pyserial ports on pty pairs joined by the link emulator."""

    settle = 0.2

    def __init__(self) -> None:
        super().__init__()
        self.emulator = LinkEmulator(seed=7)
        self._emulated: dict[int, int] = {}

    def _new_endpoint(self) -> Transport:
        return SerialTransport(self.codec)

    def _link(self, link_id: int, a: Transport, a_conn: int, b: Transport, b_conn: int) -> None:
        em = self.emulator.add_link()
        self._emulated[link_id] = em.link_id
        a.attach(a_conn, PortEnd(em.paths[0]))
        b.attach(b_conn, PortEnd(em.paths[1]))

    def inject_garbage(self, link_id: int, to_side: int, units: tuple[bytes, ...]) -> None:
        for u in units:
            self.emulator.inject(self._emulated[link_id], to_side, u + b"\x00")

    def close(self) -> None:
        super().close()
        self.emulator.close()


class TestInprocContract(TransportContract):
    def make_harness(self) -> TransportHarness:
        return InprocHarness()


class TestVirtualCanContract(TransportContract):
    def make_harness(self) -> TransportHarness:
        return CanHarness("virtual")


class TestVirtualCanFdContract(TransportContract):
    def make_harness(self) -> TransportHarness:
        return CanHarness("virtual", fd=True)


class TestSerialContract(TransportContract):
    def make_harness(self) -> TransportHarness:
        return SerialHarness()


_SOCKETCAN_PROBLEM = socketcan_problem("vcan0")


@pytest.mark.skipif(_SOCKETCAN_PROBLEM is not None, reason=f"SocketCAN vcan0 unavailable: {_SOCKETCAN_PROBLEM}")
class TestSocketCanContract(TransportContract):
    def make_harness(self) -> TransportHarness:
        return CanHarness("socketcan", channel="vcan0")
