"""An animated GIF written frame by frame: memory stays one frame however long the run.

:class:`GifStream` writes the GIF89a header with one global palette when the first frame
arrives, then each frame as soon as the next one is known (a frame identical to the one
before only lengthens its delay), and the trailer on :meth:`close`. Each frame is stored as
the rectangle that changed since the frame before (disposal "leave in place"), so a fixed
camera's static floor costs nothing after the first frame.

Frames are RGB images; each is mapped to the palette (no dithering, so an unchanged pixel
keeps its index). The palette is the first frame's own (up to ``colors`` colours by median
cut) plus :data:`RESERVED` colours, which overlays can rely on. Pixel data is LZW-coded by
Pillow (a single-frame GIF of the changed rectangle, saved to memory, whose image data this
module copies); the container is written here.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import BinaryIO

from PIL import Image, ImageChops

from dh2rt.errors import RecordError

#: Colours every palette holds (overlay text and markers): black, white, marker red.
RESERVED: tuple[tuple[int, int, int], ...] = ((0, 0, 0), (255, 255, 255), (220, 30, 30))


def _image_data(frame: Image.Image) -> bytes:
    """The LZW-coded image data (minimum code size and sub-blocks) of a P-mode image."""
    buf = io.BytesIO()
    frame.save(buf, format="GIF", optimize=False, interlace=False)  # the descriptor written here says not interlaced
    data = buf.getvalue()
    pos = 13
    if data[10] & 0x80:  # global colour table
        pos += 3 * (2 << (data[10] & 0x07))
    while data[pos] == 0x21:  # extensions: skip label, then the sub-blocks
        pos += 2
        while data[pos]:
            pos += data[pos] + 1
        pos += 1
    if data[pos] != 0x2C:
        raise RecordError(f"GIF frame: unexpected block 0x{data[pos]:02x} from the encoder")
    packed = data[pos + 9]
    pos += 10
    if packed & 0x80:  # local colour table
        pos += 3 * (2 << (packed & 0x07))
    end = pos + 1
    while data[end]:
        end += data[end] + 1
    return data[pos : end + 1]


class GifStream:
    """Writes RGB frames of one size to ``path`` as a looping GIF, one frame held at most."""

    def __init__(self, path: Path, size: tuple[int, int], delay_ms: int, *, colors: int = 61) -> None:
        if not 1 <= colors <= 256 - len(RESERVED):
            raise RecordError(f"colors must be between 1 and {256 - len(RESERVED)}, got {colors}")
        self.path = Path(path)
        self.size = size
        self.delay_cs = max(2, round(delay_ms / 10))  # browsers play < 2 cs as 10 cs
        self.colors = colors
        self.frames = 0  #: frames added (identical ones included)
        self.bytes = 0  #: bytes written so far
        self._fp: BinaryIO | None = None
        self._palette: Image.Image | None = None
        self._last: Image.Image | None = None  # the last frame as palette indices (mode L)
        self._pending: tuple[tuple[int, int, int, int], bytes, int] | None = None  # box, data, delay
        self._closed = False

    def _open(self, first: Image.Image) -> None:
        adaptive = first.quantize(colors=self.colors, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        rgb = list((adaptive.getpalette() or [])[: 3 * self.colors])
        rgb += [0] * (3 * self.colors - len(rgb))
        for colour in RESERVED:
            rgb.extend(colour)
        rgb += [0] * (768 - len(rgb))
        self._palette = Image.new("P", (1, 1))
        self._palette.putpalette(rgb)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fp = self._fp = open(self.path, "wb")  # noqa: SIM115  # closed by close()
        w, h = self.size
        fp.write(b"GIF89a" + struct.pack("<HHBBB", w, h, 0xF7, 0, 0) + bytes(rgb))
        fp.write(b"\x21\xff\x0bNETSCAPE2.0\x03\x01\x00\x00\x00")  # loop forever
        self.bytes = fp.tell()

    def add(self, frame: Image.Image) -> None:
        """Append one frame (RGB, of :attr:`size`)."""
        if self._closed:
            raise RecordError(f"{self.path}: the GIF is closed")
        if frame.size != self.size:
            raise RecordError(f"{self.path}: frame of {frame.size}, expected {self.size}")
        if self._fp is None:
            self._open(frame.convert("RGB"))
        assert self._palette is not None
        indexed = frame.convert("RGB").quantize(palette=self._palette, dither=Image.Dither.NONE)
        plain = Image.frombytes("L", self.size, indexed.tobytes())
        self.frames += 1
        box = (0, 0, *self.size) if self._last is None else ImageChops.difference(plain, self._last).getbbox()
        self._last = plain
        if box is None:  # nothing changed: show the frame before for longer
            assert self._pending is not None
            rect, data, delay = self._pending
            self._pending = (rect, data, delay + self.delay_cs)
            return
        self._flush()
        self._pending = (box, _image_data(indexed.crop(box)), self.delay_cs)

    def _flush(self) -> None:
        if self._pending is None or self._fp is None:
            return
        (x0, y0, x1, y1), data, delay = self._pending
        self._pending = None
        fp = self._fp
        # graphics control: leave the frame in place, delay in centiseconds (at most 655 s)
        fp.write(struct.pack("<BBBBHBB", 0x21, 0xF9, 4, 0x04, min(delay, 0xFFFF), 0, 0))
        fp.write(struct.pack("<BHHHHB", 0x2C, x0, y0, x1 - x0, y1 - y0, 0))
        fp.write(data)
        self.bytes = fp.tell()

    def close(self) -> Path:
        """Write what is pending and the trailer; return the path."""
        if self._closed:
            return self.path
        if self._fp is None:
            raise RecordError(f"{self.path}: no frames captured")
        self._flush()
        self._fp.write(b"\x3b")
        self.bytes = self._fp.tell()
        self._fp.close()
        self._closed = True
        return self.path

    def abandon(self) -> None:
        """Close and remove a partly written file (the run failed)."""
        if self._fp is not None and not self._fp.closed:
            self._fp.close()
            self.path.unlink(missing_ok=True)
        self._closed = True
