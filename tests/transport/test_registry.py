"""The lazy transport registry, transport specs, and SocketCAN's unavailability report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dh2rt.errors import TransportError, TransportUnavailable
from dh2rt.testing import contract_codec
from dh2rt.transport import (
    TRANSPORTS,
    BusEnd,
    Transport,
    open_transport,
    parse_spec,
    transport_class,
)
from dh2rt.transport.can_bus import socketcan_problem

ROOT = Path(__file__).resolve().parents[2]


def test_importing_transports_imports_no_hardware_library() -> None:
    code = (
        "import sys, dh2rt.transport, dh2rt.wire, dh2rt.testing\n"
        "bad = [m for m in ('can', 'serial', 'isotp', 'msgpack') if m in sys.modules]\n"
        "assert not bad, bad\n"
        "dh2rt.transport.open_transport('inproc', dh2rt.testing.contract_codec()).close()\n"
        "assert 'can' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


@pytest.mark.parametrize("name", sorted(TRANSPORTS))
def test_every_name_resolves_to_a_transport(name: str) -> None:
    cls = transport_class(name)
    assert issubclass(cls, Transport) and cls.name == name


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("inproc", ("inproc", {})),
        ("virtual:robot", ("virtual", {"channel": "robot"})),
        ("udp", ("udp", {})),
        ("socketcan:can1", ("socketcan", {"channel": "can1"})),
        ("vcan0", ("socketcan", {"channel": "vcan0"})),
        ("can0", ("socketcan", {"channel": "can0"})),
        ("serial", ("serial", {})),
    ],
)
def test_parse_spec(spec: str, expected: tuple[str, dict[str, str]]) -> None:
    assert parse_spec(spec) == expected


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("carrier-pigeon", "unknown transport"),
        ("virtual:", "empty channel"),
        ("serial:x", "no channel"),
    ],
)
def test_bad_specs_are_named(spec: str, message: str) -> None:
    with pytest.raises(TransportError, match=message):
        parse_spec(spec)


def test_socketcan_unavailable_explains_itself() -> None:
    problem = socketcan_problem("vcan0")
    if problem is None:
        pytest.skip("this machine has SocketCAN vcan0; the unavailability path cannot be shown")
    with pytest.raises(TransportUnavailable) as info:
        open_transport("vcan0", contract_codec())
    text = str(info.value)
    assert problem in text
    assert "sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; sudo ip link set up vcan0" in text
    assert "inproc" in text and "virtual" in text and "udp" in text


def test_missing_interface_is_reported() -> None:
    problem = socketcan_problem("nosuchcan7")
    assert problem is not None and ("AF_CAN" in problem or "nosuchcan7" in problem)


def test_attach_validates_connector_and_end() -> None:
    with open_transport("inproc", contract_codec(), channel="test-registry") as t:
        with pytest.raises(TransportError, match="connector 5"):
            t.attach(5, BusEnd(1, 0))
        with pytest.raises(TransportError, match="expected a BusEnd"):
            t.attach(1, "/dev/ttyS0")  # type: ignore[arg-type]
        with pytest.raises(TransportError, match="side 2"):
            BusEnd(1, 2)


def test_inproc_undock_silences_a_link() -> None:
    from dh2rt.testing import CAT
    from dh2rt.transport.inproc import InprocBus, InprocTransport

    bus = InprocBus()
    with (
        InprocTransport(contract_codec(), bus=bus) as a,
        InprocTransport(contract_codec(), bus=bus) as b,
    ):
        a.attach(2, BusEnd(9, 0))
        b.attach(1, BusEnd(9, 1))
        bus.undock(9)
        assert a.send(2, CAT) is True
        assert b.poll() == []
        bus.dock(9)
        assert a.send(2, CAT) is True
        assert len(b.poll()) == 1
        with pytest.raises(TransportError, match="already attached"):
            InprocTransport(contract_codec(), bus=bus).attach(1, BusEnd(9, 1))


def test_a_bus_poll_takes_every_frame_for_this_module_past_frames_for_others() -> None:
    """python-can filters in software on most interfaces and stops a zero-timeout read at the
    first frame it drops: a poll must still take in this module's frames queued behind one for
    another link (they used to wait for the next poll, a cycle late)."""
    import can

    from dh2rt.hormone import Hormone
    from dh2rt.transport.base import BusEnd
    from dh2rt.wire.can_frames import SINGLE, make_arbitration_id

    channel = "registry-interleaved"
    codec = contract_codec()
    a, b = open_transport(f"virtual:{channel}", codec), open_transport(f"virtual:{channel}", codec)
    other = can.Bus(interface="virtual", channel=channel)
    try:
        a.attach(1, BusEnd(5, 0))
        b.attach(2, BusEnd(5, 1))
        b.send(2, Hormone("N", (1,)))
        foreign = make_arbitration_id(0, SINGLE, 0, 9, 1)  # another link's frame, between the two
        other.send(can.Message(arbitration_id=foreign, data=b"\x12\x00", is_extended_id=True))
        b.send(2, Hormone("N", (2,)))
        got = a.poll(0.5)
        assert [r.frame for r in got] == [Hormone("N", (1,)), Hormone("N", (2,))]
    finally:
        other.shutdown()
        a.close()
        b.close()
