"""The values a rollout is made of and hands out: what an image and a program are, its timing,
the actions a host carries out (:data:`Action`) and the counters.

Shared by the module's state machine (:mod:`dh2rt.flash.rollout`), the flasher's
(:mod:`dh2rt.flash.flasher`) and their hosts (:mod:`firmware.flash.module_host`,
:mod:`firmware.flash.cable`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from dh2rt.signed_image import parse as parse_image
from dh2rt.wire.transfer import image_id, restamp_commit, tag_of

# ---------------------------------------------------------------------------------------------
# Images and programs


@dataclass(frozen=True, slots=True)
class ImageInfo:
    """What an OFFER says of an image, and what a partial image is persisted with."""

    image: bytes
    version: int
    length: int
    segment_size: int

    @property
    def count(self) -> int:
        """Segments in the image."""
        return -(-self.length // self.segment_size)

    @property
    def tag(self) -> int:
        return tag_of(self.image)

    def span(self, index: int) -> tuple[int, int]:
        """Byte offsets of segment ``index``: start, end."""
        start = index * self.segment_size
        return start, min(start + self.segment_size, self.length)


@dataclass(frozen=True, slots=True)
class Program:
    """A program a module runs: its version, its Hello digest, and the signed image it came
    from (None when the module cannot offer it, e.g. an unsigned development program)."""

    version: int
    digest: bytes
    image: bytes | None = None
    ident: bytes | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "ident", None if self.image is None else image_id(self.image))

    @classmethod
    def from_image(cls, data: bytes) -> Program:
        """The program of a signed (or unsigned) image; raises SignedImageError."""
        parsed = parse_image(data)
        return cls(parsed.version, parsed.digest, bytes(data))

    def runs(self, version: int | None, digest: bytes) -> bool:
        """Whether a neighbour whose Hello states ``version`` and ``digest`` runs this program:
        the digest names the program, the version tells this image from the same program
        signed again (flashing the same program at a new version must not switch a module at
        once because its neighbours run the old one). A Hello without a version: digest only."""
        return digest == self.digest and (version is None or version == self.version)


@dataclass(frozen=True, slots=True)
class Partial:
    """An image received in part: its info and the bytes of its first segments (what the
    :class:`Persist` actions wrote), given back to a restarted module."""

    info: ImageInfo
    data: bytes


# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True, slots=True)
class Timing:
    """Timing in cycles (calls to ``tick``) and the transfer window.

    ``rto_ticks``: an unacknowledged segment, OFFER or REPORT goes again after this many.
    ``stall_ticks``: a peer that answered nothing this long is given up (a transfer to it
    stalls, a source is replaced). ``window``: segments in flight per hop. ``linger_ticks``:
    COMMITs are re-sent this long after the switch instant. ``tolerate_ticks``: after its
    switch, a module tolerates neighbours on its old program this long."""

    rto_ticks: int = 3
    stall_ticks: int = 25
    window: int = 8
    linger_ticks: int = 50
    tolerate_ticks: int = 3

    def __post_init__(self) -> None:
        if self.rto_ticks < 1 or self.stall_ticks <= 2 * self.rto_ticks:
            raise ValueError(f"need rto_ticks >= 1 and stall_ticks > 2 * rto_ticks, got {self}")
        if not 1 <= self.window <= 64 or self.linger_ticks < 0 or self.tolerate_ticks < 1:
            raise ValueError(f"need window in 1..64, linger_ticks >= 0 and tolerate_ticks >= 1, got {self}")


# ---------------------------------------------------------------------------------------------
# Actions


@dataclass(frozen=True, slots=True)
class Send:
    """Send this transfer frame through ``connector``.

    A COMMIT states the time left to the switch instant as it leaves, so it carries that
    instant (``commit_at``, on this node's clock) and the host stamps it with its own clock
    as it transmits (:meth:`frame`): however long a busy host takes between the state machine's
    decision and the send, it is never added to the instant the next module agrees."""

    connector: int
    data: bytes
    commit_at: float | None = None

    def frame(self, now: float) -> bytes:
        """The bytes to transmit at ``now`` (the host's clock): ``data``, a COMMIT stamped."""
        if self.commit_at is None:
            return self.data
        return restamp_commit(self.data, self.commit_at - now)


@dataclass(frozen=True, slots=True)
class Persist:
    """Write ``data`` at ``offset`` of the partial image ``info`` names (offset 0: start a
    new one, dropping any other), durably: a restarted module resumes from it."""

    info: ImageInfo
    offset: int
    data: bytes


@dataclass(frozen=True, slots=True)
class DropPartial:
    """The partial image is no longer needed (staged, refused, superseded or corrupt)."""


@dataclass(frozen=True, slots=True)
class Stage:
    """Every byte is in: stage ``data`` (``Flash.stage``) and tell :meth:`Rollout.staged`."""

    info: ImageInfo
    data: bytes


@dataclass(frozen=True, slots=True)
class Switch:
    """Start the staged program this cycle (``Flash.boot`` boots it on trial), then announce
    it with a Hello carrying ``program.version`` and ``program.digest``."""

    program: Program


@dataclass(frozen=True, slots=True)
class Declined:
    """An offered image was refused before a byte of it crossed: its version is lower than
    the one here (``rollback``), or another program runs on trial (``busy``). Told once per
    image, for the host to count and log as its flash counts the images it refuses."""

    version: int
    verdict: str
    reason: str


Action = Send | Persist | DropPartial | Stage | Switch | Declined


@dataclass(slots=True)
class RolloutCounters:
    """Totals since the state machine started."""

    frames_in: int = 0
    garbage: int = 0  # frames that did not decode
    unwanted: int = 0  # frames about images not in progress here, REQUESTs for images not held
    segments_sent: int = 0
    retransmits: int = 0
    stalls: int = 0  # transfers given up (peer silent)
    corrupt_images: int = 0  # complete images whose id did not match (started over)
    reports_forwarded: int = 0
    reports_dropped: int = 0  # misrouted, or addressed past the entry point
    looped: int = 0  # offers declined because the offerer's name ran through this module
    units_sent: int = 0  # link units (Pacing.cost) of every frame sent
