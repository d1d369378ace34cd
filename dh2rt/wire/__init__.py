"""Wire codecs, sans-IO: bytes in, frames out, no I/O and no third-party imports.

* :mod:`dh2rt.wire.frame`: the frame format every link carries (hormone, keep-alive, hello).
* :mod:`dh2rt.wire.serial_framing`: COBS + CRC-32 framing for point-to-point serial links.
* :mod:`dh2rt.wire.can_frames`: CAN arbitration ids, segmentation, reassembly, pcap files.
"""

from dh2rt.wire.frame import (
    HELLO_DIGEST_BYTES,
    WIRE_VERSION,
    Decoded,
    Frame,
    FrameCodec,
    FrameKind,
    Hello,
    KeepAlive,
    frame_kind,
    program_digest,
)

__all__ = [
    "HELLO_DIGEST_BYTES",
    "WIRE_VERSION",
    "Decoded",
    "Frame",
    "FrameCodec",
    "FrameEncodeError",
    "FrameKind",
    "Hello",
    "KeepAlive",
    "frame_kind",
    "program_digest",
]
