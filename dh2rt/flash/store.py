"""The bytes of one image a node holds: :class:`Store`, segment by segment."""

from __future__ import annotations

from dh2rt.flash.values import ImageInfo
from dh2rt.wire.transfer import SACK_BITS


class Store:
    """The segments of one image held so far (every one when complete). ``released``: the
    last segment may be forwarded (the image is this module's: staged, running, or the
    entry point's)."""

    __slots__ = ("_segments", "contiguous", "info", "released")

    def __init__(self, info: ImageInfo, prefix: bytes = b"", *, released: bool = False) -> None:
        if len(prefix) > info.length or (len(prefix) % info.segment_size and len(prefix) != info.length):
            raise ValueError(f"a partial image of {len(prefix)} bytes is no run of whole segments of {info}")
        self.info = info
        self.released = released
        self._segments: dict[int, bytes] = {}
        self.contiguous = 0
        for i in range(info.count):
            start, end = info.span(i)
            if end > len(prefix):
                break
            self._segments[i] = bytes(prefix[start:end])
        self._advance()

    @property
    def complete(self) -> bool:
        return self.contiguous == self.info.count

    def add(self, index: int, data: bytes) -> bool:
        """Hold segment ``index``; False if held already. Raises ValueError for a segment
        that does not fit the image."""
        if not 0 <= index < self.info.count:
            raise ValueError(f"segment {index} of an image of {self.info.count}")
        start, end = self.info.span(index)
        if len(data) != end - start:
            raise ValueError(f"segment {index} of {len(data)} bytes, expected {end - start}")
        if index in self._segments:
            return False
        self._segments[index] = bytes(data)
        self._advance()
        return True

    def _advance(self) -> None:
        while self.contiguous in self._segments:
            self.contiguous += 1

    def segment(self, index: int) -> bytes:
        return self._segments[index]

    def run(self, first: int, end: int) -> bytes:
        """The bytes of segments ``first`` .. ``end - 1`` (all held)."""
        return b"".join(self._segments[i] for i in range(first, end))

    def assemble(self) -> bytes:
        return self.run(0, self.info.count)

    def prefix(self) -> bytes:
        """The bytes held from the first on."""
        return self.run(0, self.contiguous)

    def resized(self, segment_size: int) -> Store:
        """The same bytes cut into segments of ``segment_size`` (the whole ones held)."""
        info = ImageInfo(self.info.image, self.info.version, self.info.length, segment_size)
        data = self.prefix()
        return Store(info, data if len(data) == info.length else data[: len(data) // segment_size * segment_size])

    def sack(self) -> int:
        """The ACK bitmap: bit i set when segment ``contiguous + 1 + i`` is held."""
        base = self.contiguous + 1
        return sum(1 << i for i in range(SACK_BITS) if base + i in self._segments)

    def available(self, cut_through: bool) -> int:
        """Segments that may be sent on: all once released; else the run held from the
        first, but never the last (or none without cut-through)."""
        if self.released:
            return self.contiguous
        return min(self.contiguous, self.info.count - 1) if cut_through else 0
