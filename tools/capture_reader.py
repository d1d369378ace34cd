"""Reading captures, streaming: pcapng (CAN frames and the serial links' frames, with the
program images in its section header, as :mod:`tools.pcapng` writes it), pcap (link type
227) and every log format python-can reads (candump ``.log``, ``.asc``, ``.blf``, ``.csv``,
``.trc``, through ``can.LogReader``). Frames come one at a time, so memory stays constant
whatever the length of the capture.

A capture in a format with no room for program images has them in a sidecar file beside it,
``CAPTURE.programs.json`` (:func:`write_sidecar`).

A file that is not what it claims, or ends in the middle of a record, raises
:class:`~dh2rt.errors.CaptureError` naming the file and the byte offset (pcap, pcapng) or
the record.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, NamedTuple

from dh2rt.errors import CaptureError, DecodeError
from dh2rt.lang.image import MAGIC as IMAGE_MAGIC
from dh2rt.output_paths import shown_path
from tools import serial_records
from tools.pcap import CAN_EFF_FLAG, LINKTYPE_CAN_SOCKETCAN
from tools.pcapng import LINKTYPE_USER0, PcapngReader
from tools.serial_records import SerialRecord

_PCAP_MAGICS = {0xA1B2C3D4: 1e-6, 0xA1B23C4D: 1e-9}
#: The suffixes python-can's LogReader knows (and what it makes of them).
PYTHON_CAN_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc", ".db")


class CanRecord(NamedTuple):
    """One CAN frame of a capture."""

    timestamp: float
    arbitration_id: int
    data: bytes
    is_extended_id: bool


#: What a capture holds: CAN frames, and frames of the emulated serial links.
Record = CanRecord | SerialRecord
SIDECAR_SUFFIX = ".programs.json"
SIDECAR_FORMAT = "dh2rt-capture-programs"


def read_records(path: Path) -> Iterator[Record]:
    """The frames of a capture file, in file order: CAN frames and serial link frames. The
    file is opened (and an error raised) when the first frame is asked for."""
    # the reader's own generator, not one that delegates to it: a layer less for every frame
    if path.suffix.lower() == ".pcapng":
        return _read_pcapng(path)
    return read_can(path)


_SOCKETCAN_HEAD = struct.Struct(">IB")  # the id with its flags, the data length


def _read_pcapng(path: Path) -> Iterator[Record]:
    new = tuple.__new__  # CanRecord(...) without its Python-level __new__: this runs for every frame
    with _open(path) as fh:
        reader = PcapngReader(fh, path)
        reader.read_header()
        for packet in reader:
            if packet.linktype == LINKTYPE_CAN_SOCKETCAN:
                data = packet.data
                if len(data) < 8:
                    raise CaptureError(f"{path}: offset {packet.offset}: CAN packet of {len(data)} bytes")
                can_id, length = _SOCKETCAN_HEAD.unpack_from(data)
                if length > len(data) - 8:
                    raise CaptureError(f"{path}: offset {packet.offset}: CAN frame claims {length} bytes")
                extended = bool(can_id & CAN_EFF_FLAG)
                can_id &= 0x1FFFFFFF if extended else 0x7FF
                yield new(CanRecord, (packet.timestamp, can_id, data[8 : 8 + length], extended))
            elif packet.linktype == LINKTYPE_USER0:
                try:
                    yield serial_records.unpack(packet.timestamp, packet.data)
                except DecodeError as exc:
                    raise CaptureError(f"{path}: offset {packet.offset}: {exc}") from None
            else:
                raise CaptureError(
                    f"{path}: offset {packet.offset}: link type {packet.linktype} is neither CAN (227) "
                    f"nor dh2rt serial ({LINKTYPE_USER0})"
                )


def capture_programs(path: Path) -> list[bytes]:
    """The program images a capture carries: in a pcapng's section header, or in the sidecar."""
    if path.suffix.lower() == ".pcapng":
        with _open(path) as fh:
            reader = PcapngReader(fh, path)
            reader.read_header()
            return [c for c in reader.comments if c.startswith(IMAGE_MAGIC)]
    _check_exists(path)
    sidecar = sidecar_path(path)
    try:
        if not sidecar.exists():
            return []
        doc = json.loads(sidecar.read_text(encoding="utf-8"))
        if doc.get("format") != SIDECAR_FORMAT:
            raise ValueError(f"format is {doc.get('format')!r}, expected {SIDECAR_FORMAT!r}")
        return [str(p["image"]).encode("ascii") for p in doc["programs"]]
    except (ValueError, KeyError, TypeError, AttributeError, UnicodeError) as exc:
        raise CaptureError(f"{sidecar}: not a dh2rt programs file ({exc})") from None
    except OSError as exc:
        raise CaptureError(f"{shown_path(sidecar)}: cannot be read ({exc.strerror or exc})") from None


def sidecar_path(path: Path) -> Path:
    return path.with_name(path.name + SIDECAR_SUFFIX)


def write_sidecar(path: Path, programs: Sequence[bytes]) -> Path:
    """Write the program images of the capture ``path`` beside it; returns the sidecar's path."""
    from dh2rt.wire.frame import program_digest

    doc = {
        "format": SIDECAR_FORMAT,
        "version": 1,
        "programs": [{"digest": program_digest(p).hex(), "image": p.decode("ascii")} for p in programs],
    }
    target = sidecar_path(path)
    target.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return target


def read_can(path: Path) -> Iterator[CanRecord]:
    """The CAN frames of a pcap or python-can log file, in file order. The file is opened (and
    an error raised) when the first frame is asked for."""
    suffix = path.suffix.lower()
    if suffix in (".pcap", ".cap"):
        return _read_pcap(path)
    if suffix in PYTHON_CAN_SUFFIXES:
        return _read_python_can(path)
    return _unknown_format(path)


def _check_exists(path: Path) -> None:
    """Raise CaptureError unless ``path`` is a file that can be read (no traceback for a name
    too long, a folder or a file not to be read)."""
    _open(path).close()


def _open(path: Path) -> BinaryIO:
    try:
        return path.open("rb")
    except FileNotFoundError:
        raise CaptureError(f"{shown_path(path)}: no such capture file") from None
    except OSError as exc:
        raise CaptureError(f"{shown_path(path)}: cannot be read as a capture ({exc.strerror or exc})") from None


def _unknown_format(path: Path) -> Iterator[CanRecord]:
    _check_exists(path)
    known = ", ".join((".pcapng", ".pcap", *PYTHON_CAN_SUFFIXES))
    raise CaptureError(f"{path}: unknown capture format {path.suffix.lower() or '(no suffix)'} (known: {known})")
    yield  # a generator, like the readers: nothing happens before the first frame is asked for


def _read_pcap(path: Path) -> Iterator[CanRecord]:
    with _open(path) as fh:
        yield from _pcap_records(fh, path)


def _pcap_records(fh: BinaryIO, path: Path) -> Iterator[CanRecord]:
    head = fh.read(24)
    if len(head) < 24:
        raise CaptureError(f"{path}: offset 0: shorter than a pcap header (24 bytes)")
    for endian in ("<", ">"):
        magic = struct.unpack(endian + "I", head[:4])[0]
        if magic in _PCAP_MAGICS:
            scale = _PCAP_MAGICS[magic]
            break
    else:
        raise CaptureError(f"{path}: offset 0: not a pcap file (magic {head[:4].hex()})")
    linktype = struct.unpack(endian + "I", head[20:24])[0] & 0x0FFFFFFF
    if linktype != LINKTYPE_CAN_SOCKETCAN:
        raise CaptureError(f"{path}: offset 20: link type {linktype}, expected {LINKTYPE_CAN_SOCKETCAN} (SocketCAN)")
    offset = 24
    record = struct.Struct(endian + "IIII")
    while True:
        rec = fh.read(16)
        if not rec:
            return
        if len(rec) < 16:
            raise CaptureError(f"{path}: offset {offset}: record header cut short ({len(rec)} of 16 bytes)")
        sec, frac, incl, _orig = record.unpack(rec)
        body = fh.read(incl)
        if len(body) < incl:
            raise CaptureError(f"{path}: offset {offset}: record cut short ({len(body)} of {incl} bytes)")
        if incl < 8:
            raise CaptureError(f"{path}: offset {offset}: record of {incl} bytes has no CAN header")
        can_id, length = struct.unpack(">IB", body[:5])
        if length > incl - 8:
            raise CaptureError(f"{path}: offset {offset}: CAN frame claims {length} bytes, the record has {incl - 8}")
        extended = bool(can_id & CAN_EFF_FLAG)
        can_id &= 0x1FFFFFFF if extended else 0x7FF
        yield CanRecord(sec + frac * scale, can_id, body[8 : 8 + length], extended)
        offset += 16 + incl


def _read_python_can(path: Path) -> Iterator[CanRecord]:
    import can

    _check_exists(path)
    if path.suffix.lower() == ".blf":
        # python-can's BLF reader leaves the file open when the header is wrong: look first
        with _open(path) as fh:
            if fh.read(4) != b"LOGG":
                raise CaptureError(f"{path}: offset 0: not a BLF file (no LOGG signature)")

    try:
        reader = can.LogReader(str(path))
    except Exception as exc:  # python-can raises what its parsers raise: name the file
        raise CaptureError(f"{path}: python-can cannot read it ({type(exc).__name__}: {exc})") from None
    new = tuple.__new__  # CanRecord(...) without its Python-level __new__: this runs for every frame
    count = 0
    try:
        for msg in reader:
            count += 1
            fields = (float(msg.timestamp), int(msg.arbitration_id), bytes(msg.data), bool(msg.is_extended_id))
            yield new(CanRecord, fields)
    except CaptureError:
        raise
    except Exception as exc:
        raise CaptureError(f"{path}: record {count}: python-can cannot read it ({type(exc).__name__}: {exc})") from None
    finally:
        stop = getattr(reader, "stop", None)
        if callable(stop):
            stop()
