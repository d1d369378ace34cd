"""The program images a flash carried, rebuilt from a capture's transfer frames.

A flash sends the signed image over the robot's own links: every module's OFFER names the
image (its id, length and segment size, the version) and its SEGMENTs carry the bytes, each
hop sending them again. A capture that holds every segment of an image, on any link, holds
the image: :func:`images_on_the_wire` joins them, checks the join against the id the OFFER
named (the first 8 bytes of its blake2b, as a module checks what it received) and reads the
program out of it. Replay then runs that program from the cycle a module switched to it,
without ``--flashed``.

An image with a segment missing everywhere (the capture began or ended during the transfer)
is said, with how many segments of how many are there, and not guessed at. An image that
does not read as a program is said too. Whether its signature holds is for ``--trust``: a
module refused it or ran it, and the capture shows which.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from dh2rt.compiler import load_image
from dh2rt.errors import DecodeError, DH2Error
from dh2rt.program import CompiledProgram
from dh2rt.signed_image import SignedImage, parse
from dh2rt.wire.transfer import Offer, Segment, image_id, tag_of
from dh2rt.wire.transfer import decode as decode_transfer
from tools.capture_reader import read_records
from tools.decode import Decoder, Hop


@dataclass(frozen=True)
class WireImage:
    """An image a capture's OFFERs named: its bytes when every segment is there (None
    otherwise), the program in it (None: none rebuilt), and what replay says of it."""

    image_id: bytes
    version: int
    signed: SignedImage | None
    program: CompiledProgram | None
    note: str


class _Collector(Decoder):
    """A decoder that keeps the OFFERs and SEGMENTs of the transfer frames it decodes."""

    def __init__(self, programs: Sequence[CompiledProgram]) -> None:
        super().__init__(programs)  # a frame the memo holds is a copy of one collected already
        self.offers: dict[bytes, Offer] = {}
        self.segments: dict[tuple[int, int], bytes] = {}

    def _family(self, rec_time: float, key: tuple[str, int, int], payload: bytes, note: str, kind: str) -> Hop:
        if kind == "transfer":
            try:
                _, message = decode_transfer(payload)
            except DecodeError:
                pass  # the hop says so
            else:
                if isinstance(message, Offer):
                    self.offers.setdefault(message.image, message)
                elif isinstance(message, Segment):
                    self.segments.setdefault((message.tag, message.index), message.data)
        return super()._family(rec_time, key, payload, note, kind)


def images_on_the_wire(path: Path, programs: Sequence[CompiledProgram]) -> list[WireImage]:
    """Every image the capture's OFFERs name, in the order first offered (module docs)."""
    collector = _Collector(programs)
    for _ in collector.hops(read_records(path)):
        pass
    return [_join(offer, collector.segments) for offer in collector.offers.values()]


def _join(offer: Offer, segments: dict[tuple[int, int], bytes]) -> WireImage:
    named = offer.image.hex()
    count = math.ceil(offer.length / offer.segment_size) if offer.segment_size else 0
    tag = tag_of(offer.image)
    held = [segments.get((tag, i)) for i in range(count)]
    present = [part for part in held if part is not None]
    if len(present) < count:
        note = f"image {named} (version {offer.version}): {len(present)} of its {count} segments are in the capture"
        return WireImage(offer.image, offer.version, None, None, note)
    data = b"".join(present)[: offer.length]
    if image_id(data) != offer.image:
        note = f"image {named}: its segments joined do not make the image its OFFER named (another image's tag?)"
        return WireImage(offer.image, offer.version, None, None, note)
    try:
        signed = parse(data)
        program = load_image(signed.program())
    except DH2Error as exc:
        return WireImage(offer.image, offer.version, None, None, f"image {named}: not a program image ({exc})")
    note = (
        f"image {named}: program {program.name} version {signed.version}, rebuilt from {count} segments "
        "of the capture's transfer frames"
    )
    return WireImage(offer.image, signed.version, signed, program, note)
