"""Serial framing for point-to-point links (infrared emulation), sans-IO.

On the wire each frame is ``COBS(payload + FCS) + b"\\x00"``: the frame check sequence is
CRC-32 (ISO-HDLC, as HDLC's FCS-32 and Ethernet: ``binascii.crc32``, little-endian) over the
payload, and COBS removes every zero byte so that ``0x00`` only ever delimits frames. A
caterpillar hormone's 4-byte payload becomes 10 bytes on the wire: COBS code byte, 4 payload
bytes, 4 FCS bytes, delimiter.

Why CRC-32 with a final XOR: framing version 1 used CRC-16/CCITT-FALSE, which has no final
XOR, so ``crc(msg || crc_hi) == crc_lo << 8``: a one-bit error that turned the delimiter
``00`` into ``01`` made the frame decode as its payload plus one byte, with a valid CRC, every
time. A final XOR (HDLC's reason for one) removes that structure, and 32 bits leave a chance
of 2^-32 for random corruption to pass (see ``docs/link-layer.md``).

:class:`SerialDecoder` is incremental: feed it bytes as they come, in any chunks, and it
returns the payloads whose CRC holds. A corrupted frame (bad COBS, bad CRC, too short) is
counted in ``corrupted``, an over-long one in ``dropped``; either way decoding resynchronises
at the next delimiter and the result never depends on how the input was chunked.
"""

from __future__ import annotations

import binascii

from dh2rt.errors import FrameCorrupted, FrameEncodeError

#: The serial framing's version (1: CRC-16/CCITT-FALSE; 2: CRC-32), for documents and captures.
FRAMING_VERSION = 2
DELIMITER = 0x00
CRC_BYTES = 4
#: Largest payload a serial frame carries (a hormone frame is at most about 200 bytes).
MAX_PAYLOAD = 512


def fcs32(data: bytes) -> int:
    """CRC-32/ISO-HDLC (poly 0x04C11DB7 reflected, init and final XOR 0xFFFFFFFF)."""
    return binascii.crc32(data)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result has no zero byte (no delimiter added)."""
    out = bytearray()
    # COBS treats the data as if followed by one implicit zero and splits it at every zero.
    for block in data.split(b"\x00"):
        # Each zero-terminated block becomes (len+1, block); long runs split every 254 bytes.
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Undo :func:`cobs_encode`; raises FrameCorrupted for bytes no encoder produces."""
    out = bytearray()
    pos = 0
    n = len(data)
    while pos < n:
        code = data[pos]
        if code == 0:
            raise FrameCorrupted("COBS: zero byte inside a frame")
        end = pos + code
        if end > n:
            raise FrameCorrupted("COBS: code byte runs past the end of the frame")
        block = data[pos + 1 : end]
        if DELIMITER in block:
            raise FrameCorrupted("COBS: zero byte inside a frame")
        out += block
        pos = end
        # A full block (0xFF) carries no implicit zero; nor does the final block.
        if code != 0xFF and pos < n:
            out.append(0)
    return bytes(out)


def encode_serial(payload: bytes) -> bytes:
    """The bytes that carry ``payload`` over a serial link, delimiter included."""
    if len(payload) > MAX_PAYLOAD:
        raise FrameEncodeError(f"serial payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = payload + fcs32(payload).to_bytes(CRC_BYTES, "little")
    return cobs_encode(body) + b"\x00"


def decode_serial(frame: bytes) -> bytes:
    """Decode one frame without its delimiter; raises FrameCorrupted on bad COBS or CRC."""
    body = cobs_decode(frame)
    if len(body) <= CRC_BYTES:
        raise FrameCorrupted(f"serial frame of {len(body)} bytes is too short for a payload and CRC")
    payload, crc = body[:-CRC_BYTES], int.from_bytes(body[-CRC_BYTES:], "little")
    if fcs32(payload) != crc:
        raise FrameCorrupted("serial frame failed its CRC")
    return payload


#: Longest COBS-encoded frame (without its delimiter) the decoder accepts.
MAX_ENCODED = MAX_PAYLOAD + CRC_BYTES + (MAX_PAYLOAD + CRC_BYTES) // 254 + 1


class SerialDecoder:
    """Incremental frame decoder: ``feed(bytes) -> [payload, ...]``, counting bad frames."""

    __slots__ = ("_buf", "_discarding", "corrupted", "dropped", "frames", "max_encoded")

    def __init__(self, max_encoded: int = MAX_ENCODED) -> None:
        self.max_encoded = max_encoded
        self._buf = bytearray()
        self._discarding = False
        #: Frames delivered.
        self.frames = 0
        #: Frames that failed COBS or CRC (noise, bit errors, partial frames).
        self.corrupted = 0
        #: Frames discarded for being longer than ``max_encoded``.
        self.dropped = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Consume ``data``; return the payloads of the frames it completes, in order."""
        out: list[bytes] = []
        start = 0
        while True:
            idx = data.find(b"\x00", start)
            if idx < 0:
                self._append(data[start:])
                return out
            self._append(data[start:idx])
            self._finish(out)
            start = idx + 1

    def reset(self) -> None:
        """Forget any partial frame (e.g. after reopening the port)."""
        self._buf.clear()
        self._discarding = False

    @property
    def pending(self) -> int:
        """Bytes of the partial frame held."""
        return len(self._buf)

    def _append(self, chunk: bytes) -> None:
        if self._discarding or not chunk:
            return
        self._buf += chunk
        if len(self._buf) > self.max_encoded:
            self._buf.clear()
            self._discarding = True

    def _finish(self, out: list[bytes]) -> None:
        if self._discarding:
            self._discarding = False
            self.dropped += 1
            return
        if not self._buf:  # back-to-back delimiters are idle line, not frames
            return
        raw = bytes(self._buf)
        self._buf.clear()
        try:
            payload = decode_serial(raw)
        except FrameCorrupted:
            self.corrupted += 1
            return
        self.frames += 1
        out.append(payload)
