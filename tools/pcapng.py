"""pcapng files of a robot's traffic, as Wireshark and tshark read them: the capture tools'
own format, streamed in both directions (a writer that appends block by block, a reader that
yields one packet at a time).

A dh2rt capture is one section with two interfaces:

* interface 0, link type 227 (``LINKTYPE_CAN_SOCKETCAN``): CAN frames as SocketCAN hands them
  to Wireshark (8-byte header: big-endian id with the EFF/RTR/ERR flags, length, FD flags);
* interface 1, link type 147 (``LINKTYPE_USER0``): frames of the emulated infrared serial
  links, each with the 8-byte header of :mod:`tools.serial_records` (link id, the side that
  sent it, lost, corrupted) and the frame's bytes as they were on the wire (COBS, CRC-32 and
  the 0x00 delimiter).

The program images the robot ran are in the section header, one ``opt_comment`` each (an
image is ASCII: ``DH2IMG1`` and canonical JSON), so a capture decodes on another machine with
nothing else, and Wireshark shows the program under Statistics > Capture File Properties.
A reader matches an image to a link end by the Hello digest (blake2b-48 of the image).

Blocks this module does not use (name resolution, statistics, custom blocks) are skipped, as
the format asks. Errors are :class:`~dh2rt.errors.CaptureError` naming the file and offset.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, NamedTuple

from dh2rt.errors import CaptureError, EncodeError

SHB = 0x0A0D0D0A
IDB = 0x00000001
EPB = 0x00000006
BYTE_ORDER_MAGIC = 0x1A2B3C4D
OPT_END, OPT_COMMENT = 0, 1
IF_NAME, IF_DESCRIPTION, IF_TSRESOL = 2, 3, 9
SHB_USERAPPL = 4
LINKTYPE_CAN_SOCKETCAN = 227
LINKTYPE_USER0 = 147
#: The interface numbers of a dh2rt capture.
CAN_INTERFACE, SERIAL_INTERFACE = 0, 1
_MAX_OPTION = 0xFFFF
_MAX_BLOCK = 16 * 1024 * 1024
_new = tuple.__new__


def _pad(data: bytes) -> bytes:
    return data + b"\x00" * (-len(data) % 4)


def _option(code: int, value: bytes) -> bytes:
    if len(value) > _MAX_OPTION:
        raise EncodeError(f"pcapng: option {code} of {len(value)} bytes exceeds {_MAX_OPTION}")
    return struct.pack("<HH", code, len(value)) + _pad(value)


def _block(block_type: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", block_type, total) + body + struct.pack("<I", total)


class PcapngWriter:
    """Appends packets to a pcapng file; ``programs`` go in the section header."""

    def __init__(self, path: str | Path, programs: Sequence[bytes] = (), *, can_name: str = "can") -> None:
        header = self.section_header(programs)
        self._fh: BinaryIO = open(path, "wb")  # noqa: SIM115 - closed by close()
        self._fh.write(header)
        self._fh.write(_interface(LINKTYPE_CAN_SOCKETCAN, can_name, "dh2rt CAN bus (link id and side in the id)"))
        self._fh.write(_interface(LINKTYPE_USER0, "dh2rt-serial", "dh2rt emulated infrared serial links"))
        self.count = 0

    @staticmethod
    def section_header(programs: Sequence[bytes]) -> bytes:
        options = b"".join(_option(OPT_COMMENT, image) for image in programs)
        options += _option(SHB_USERAPPL, b"dh2rt") + struct.pack("<HH", OPT_END, 0)
        return _block(SHB, struct.pack("<IHHq", BYTE_ORDER_MAGIC, 1, 0, -1) + options)

    def write(self, interface: int, timestamp: float, data: bytes) -> None:
        """One packet on ``interface`` (microsecond timestamps, the pcapng default)."""
        if not 0 <= timestamp < 2**63 / 1e6:
            raise EncodeError(f"pcapng: timestamp {timestamp} is outside the format's range")
        ticks = round(timestamp * 1e6)
        body = struct.pack("<IIIII", interface, ticks >> 32, ticks & 0xFFFFFFFF, len(data), len(data))
        self._fh.write(_block(EPB, body + _pad(bytes(data))))
        self.count += 1

    def flush(self) -> None:
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def _interface(linktype: int, name: str, description: str) -> bytes:
    options = _option(IF_NAME, name.encode()) + _option(IF_DESCRIPTION, description.encode())
    options += _option(IF_TSRESOL, b"\x06") + struct.pack("<HH", OPT_END, 0)
    return _block(IDB, struct.pack("<HHI", linktype, 0, 0) + options)


class Packet(NamedTuple):
    """One packet of a pcapng file: the link type of its interface, its time, its bytes,
    and the byte offset of its block (for error messages)."""

    linktype: int
    timestamp: float
    data: bytes
    offset: int


class PcapngReader:
    """The packets of a pcapng file, in file order, and the comments of its section headers
    (:attr:`comments`, filled as sections are read: the first section's before its first
    packet)."""

    def __init__(self, fh: BinaryIO, path: Path) -> None:
        self._fh = fh
        self.path = path
        self.comments: list[bytes] = []
        self._interfaces: list[tuple[int, float]] = []  # (linktype, seconds per tick)
        self._offset = 0
        self._set_endian("<")

    def _set_endian(self, endian: str) -> None:
        """The section's byte order, and the structs every block is read with in it."""
        self._endian = endian
        self._u32 = struct.Struct(endian + "I")
        self._block_head = struct.Struct(endian + "II")
        self._epb_head = struct.Struct(endian + "IIIII")

    def _fail(self, offset: int, message: str) -> CaptureError:
        return CaptureError(f"{self.path}: offset {offset}: {message}")

    def read_header(self) -> None:
        """Read the first section header (so :attr:`comments` holds its programs)."""
        block = self._next_block()
        if block is None or block[0] != SHB:
            raise self._fail(0, "not a pcapng file (no section header block)")
        self._section(block[1], block[2])

    def __iter__(self) -> Iterator[Packet]:
        while True:
            block = self._next_block(eof_ok=True)
            if block is None:
                return
            block_type, body, offset = block
            if block_type == SHB:
                self._section(body, offset)
            elif block_type == IDB:
                self._interface(body, offset)
            elif block_type == EPB:
                yield self._packet(body, offset)
            # other blocks: skipped, as the format asks of a reader that does not know them

    def _next_block(self, eof_ok: bool = False) -> tuple[int, bytes, int] | None:
        offset = self._offset
        head = self._fh.read(8)
        if len(head) < 8:
            if not head and eof_ok:
                return None
            raise self._fail(offset, f"block header cut short ({len(head)} of 8 bytes)")
        # SHB's type reads the same in either byte order
        block_type, total = self._block_head.unpack_from(head)
        if offset == 0 and block_type != SHB:
            raise self._fail(0, f"not a pcapng file (starts with {head[:4].hex()}, not a section header block)")
        if block_type == SHB:  # the byte order is the section's: read it from the magic
            magic = self._fh.read(4)
            if len(magic) < 4:
                raise self._fail(offset, "section header cut short")
            for endian in ("<", ">"):
                if struct.unpack(endian + "I", magic)[0] == BYTE_ORDER_MAGIC:
                    self._set_endian(endian)
                    break
            else:
                raise self._fail(offset + 8, f"bad byte-order magic {magic.hex()}")
            head += magic
            block_type, total = self._block_head.unpack_from(head)
        if total < 12 or total % 4 or total > _MAX_BLOCK:
            raise self._fail(offset, f"block of type {block_type:#x} claims {total} bytes")
        rest = self._fh.read(total - len(head))
        if len(rest) < total - len(head):
            raise self._fail(offset, f"block cut short ({len(head) + len(rest)} of {total} bytes)")
        data = head[8:] + rest if len(head) > 8 else rest
        if self._u32.unpack_from(data, len(data) - 4)[0] != total:
            raise self._fail(offset, "block's trailing length differs from its leading length")
        self._offset = offset + total
        return block_type, data[:-4], offset

    def _options(self, data: bytes, offset: int) -> Iterator[tuple[int, bytes]]:
        pos = 0
        while pos + 4 <= len(data):
            code, length = struct.unpack(self._endian + "HH", data[pos : pos + 4])
            if code == OPT_END:
                return
            if pos + 4 + length > len(data):
                raise self._fail(offset, f"option {code} claims {length} bytes past the end of its block")
            yield code, data[pos + 4 : pos + 4 + length]
            pos += 4 + length + (-length % 4)

    def _section(self, body: bytes, offset: int) -> None:
        if len(body) < 16:
            raise self._fail(offset, "section header shorter than 16 bytes")
        major = struct.unpack(self._endian + "H", body[4:6])[0]
        if major != 1:
            raise self._fail(offset, f"pcapng version {major}, expected 1")
        self._interfaces = []
        for code, value in self._options(body[16:], offset):
            if code == OPT_COMMENT:
                self.comments.append(value)

    def _interface(self, body: bytes, offset: int) -> None:
        if len(body) < 8:
            raise self._fail(offset, "interface description shorter than 8 bytes")
        linktype = struct.unpack(self._endian + "H", body[:2])[0]
        scale = 1e-6
        for code, value in self._options(body[8:], offset):
            if code == IF_TSRESOL and value:
                res = value[0]
                scale = 2.0 ** -(res & 0x7F) if res & 0x80 else 10.0**-res
        self._interfaces.append((linktype, scale))

    def _packet(self, body: bytes, offset: int) -> Packet:
        if len(body) < 20:
            raise self._fail(offset, "enhanced packet block shorter than 20 bytes")
        interface, high, low, captured, _original = self._epb_head.unpack_from(body)
        if interface >= len(self._interfaces):
            raise self._fail(offset, f"packet on interface {interface}, which no interface block describes")
        if 20 + captured > len(body):
            raise self._fail(offset, f"packet claims {captured} bytes, its block has {len(body) - 20}")
        linktype, scale = self._interfaces[interface]
        # Packet(...) without the named tuple's Python-level constructor: once per packet
        return _new(Packet, (linktype, ((high << 32) | low) * scale, body[20 : 20 + captured], offset))
