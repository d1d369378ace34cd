"""The liveness state machine on its own: no transport, no engine, no clock.

Each case is a script of cycles: frames heard through connector 1 during a cycle, then the
tick; the expected outcome is checked after every cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from dh2rt.liveness import REPEATED_HELLOS, SILENCE_CYCLES, Beacon, Liveness, Verdict
from dh2rt.wire.frame import NO_PROGRAM, Frame, Hello, KeepAlive

MINE = b"\x01" * 8
OTHER = b"\x02" * 8


@dataclass
class Cycle:
    """One cycle: what arrives through connector 1, whether it is linked at the tick, and
    what must follow."""

    frames: list[Frame] = field(default_factory=list)
    linked: bool = True
    verdicts: list[Verdict] | None = None
    lost: bool = False
    beacon: type | None = None  # the kind of beacon connector 1 sends at the end of the cycle


def run_script(script: list[Cycle], silence: int = SILENCE_CYCLES) -> Liveness:
    lv = Liveness(MINE, silence)
    lv.attach(1)
    for n, cyc in enumerate(script):
        verdicts = [lv.receive(1, f, n) for f in cyc.frames]
        if cyc.verdicts is not None:
            assert verdicts == cyc.verdicts, f"cycle {n}"
        heard = {1} if Verdict.HEARD in verdicts else set()
        lost = lv.tick(heard, {1} if cyc.linked else set())
        assert bool(lost) == cyc.lost, f"cycle {n}: lost {lost}"
        beacons = lv.beacons(set(), n)
        if cyc.beacon is not None:
            assert [type(b.frame) for b in beacons] == [cyc.beacon], f"cycle {n}"
    return lv


HELLO, KEEP = Hello(MINE), KeepAlive(1)


@pytest.mark.parametrize("silence", [1, 2, 3, 5])
def test_silence_bound_is_exact(silence: int) -> None:
    """A verified, linked connector falls exactly in the silence-th silent cycle, never before."""
    script = [Cycle([HELLO], verdicts=[Verdict.HEARD])]
    script += [Cycle() for _ in range(silence - 1)]
    script += [Cycle(lost=True, beacon=Hello)]  # lost, and must announce itself again
    script += [Cycle(linked=False) for _ in range(3)]  # nothing more to lose
    lv = run_script(script, silence)
    assert not lv.verified(1)
    assert lv.counters.links_lost == 1


@pytest.mark.parametrize("gap", [1, 2, 3])
def test_any_frame_resets_silence(gap: int) -> None:
    """Frames closer together than the bound keep the link, whatever their kind."""
    script = [Cycle([HELLO])]
    for k in range(6):
        script += [Cycle() for _ in range(gap - 1)]
        script += [Cycle([KeepAlive(k + 1)], verdicts=[Verdict.HEARD])]
    lv = run_script(script, silence=3)
    assert lv.verified(1) and lv.counters.links_lost == 0


def test_unlinked_connector_is_never_lost() -> None:
    """Silence on a connector whose status is already 0 loses nothing (and counts nothing)."""
    lv = run_script([Cycle([HELLO])] + [Cycle(linked=False) for _ in range(10)])
    assert lv.counters.links_lost == 0


@pytest.mark.parametrize(
    ("frames", "verdicts", "verified", "refused", "ignored"),
    [
        ([KEEP], [Verdict.IGNORED], False, False, 1),  # a KeepAlive before any Hello
        ([HELLO, KEEP], [Verdict.HEARD, Verdict.HEARD], True, False, 0),
        ([Hello(OTHER)], [Verdict.REFUSED], False, True, 0),
        ([Hello(OTHER), KEEP], [Verdict.REFUSED, Verdict.IGNORED], False, True, 1),
        ([Hello(OTHER), HELLO], [Verdict.REFUSED, Verdict.HEARD], True, False, 0),  # peer reflashed
        ([HELLO, Hello(OTHER)], [Verdict.HEARD, Verdict.REFUSED], False, True, 0),
    ],
)
def test_hello_verifies_or_refuses(
    frames: list[Frame], verdicts: list[Verdict], verified: bool, refused: bool, ignored: int
) -> None:
    lv = Liveness(MINE)
    lv.attach(1)
    assert [lv.receive(1, f, 0) for f in frames] == verdicts
    assert lv.verified(1) is verified
    assert lv.refused(1) is refused
    assert lv.settled is (verified or refused)
    assert lv.counters.ignored == ignored
    assert lv.counters.refused == sum(v is Verdict.REFUSED for v in verdicts)


def test_unattached_connector() -> None:
    lv = Liveness(MINE)
    assert lv.receive(2, HELLO, 0) is Verdict.UNATTACHED
    assert lv.counters.ignored == 0


def test_reverification_after_redock() -> None:
    """Detached and attached again (a re-dock): the new peer must say Hello before its frames
    count, and it is greeted with a fresh Hello."""
    lv = Liveness(MINE)
    lv.attach(1)
    assert lv.receive(1, HELLO, 0) is Verdict.HEARD
    lv.detach(1)
    assert lv.receive(1, KEEP, 1) is Verdict.UNATTACHED
    lv.attach(1)  # announced by the next beacon, not at once: the peer may not listen yet
    assert lv.receive(1, KEEP, 2) is Verdict.IGNORED
    assert lv.beacons(set(), 2) == [Beacon(1, Hello(MINE))]
    assert lv.receive(1, HELLO, 3) is Verdict.HEARD
    # our Hello of cycle 2 is recent: the peer heard it, no answer is due
    assert [type(b.frame) for b in lv.beacons(set(), 3)] == [KeepAlive]


def test_a_peer_that_keeps_saying_hello_is_answered_but_two_peers_never_ping_pong() -> None:
    """A peer that says Hello again since our last one has not heard it (and drops what we
    send): it is answered at once, every REPEATED_HELLOS of its Hellos; two peers that heard
    each other say KeepAlive from then on, whatever their phase."""
    lv = Liveness(MINE, 3)
    lv.attach(1)
    lv.receive(1, HELLO, 0)
    kinds = []
    for cycle in range(12):
        lv.receive(1, HELLO, cycle)  # the peer says Hello every cycle: it never hears us
        kinds.append(type(lv.beacons(set(), cycle)[0].frame))
    assert [c for c, k in enumerate(kinds) if k is Hello] == list(range(0, 12, REPEATED_HELLOS))

    for lag in (0, 1):  # B's frames reach A in the same cycle, or a cycle late
        a, b = Liveness(MINE, 3), Liveness(MINE, 3)
        a.attach(1)
        b.attach(1)
        late: list[Frame] = []
        sent: list[tuple[str, type]] = []
        for cycle in range(20):
            for beacon in a.beacons(set(), cycle):
                b.receive(1, beacon.frame, cycle)
                sent.append(("a", type(beacon.frame)))
            for frame in late:
                a.receive(1, frame, cycle)
            late = [beacon.frame for beacon in b.beacons(set(), cycle)]
            sent += [("b", type(f)) for f in late]
            if not lag:
                for frame in late:
                    a.receive(1, frame, cycle)
                late = []
        assert a.verified(1) and b.verified(1)
        assert all(kind is KeepAlive for _, kind in sent[-20:]), (lag, sent)  # settled: no ping-pong


def test_a_first_hello_lost_is_made_good_within_a_few_cycles() -> None:
    """Our first Hello on a new link is lost (the peer's end was not attached yet): the peer
    says Hello each cycle, and has heard us three cycles later, not after silence_cycles
    (found in the loop: the peer dropped a hormone sent meanwhile, and the program stalled)."""
    a, b = Liveness(MINE, 6), Liveness(MINE, 6)
    a.attach(1)
    a.beacons(set(), 0)  # lost on the link
    b.attach(1)
    for cycle in range(1, 10):
        for beacon in b.beacons(set(), cycle):
            a.receive(1, beacon.frame, cycle)
        for beacon in a.beacons(set(), cycle):
            b.receive(1, beacon.frame, cycle)
        if b.verified(1):
            break
    assert b.verified(1) and cycle <= 3, cycle


def test_carried_connectors_send_no_beacon_and_gaps_count_missed() -> None:
    lv = Liveness(MINE)
    lv.attach(1)
    lv.attach(2)
    lv.receive(1, HELLO, 0)
    lv.receive(2, HELLO, 0)
    lv.beacons(set(), 0)  # the answers
    assert [b.connector for b in lv.beacons({1}, 1)] == [2]
    seqs = [b.frame.seq for b in lv.beacons(set(), 2) if isinstance(b.frame, KeepAlive)]
    assert seqs == [1, 2]  # numbered per connector
    for seq in (1, 2, 5, 6):  # 3 and 4 lost on the link
        assert lv.receive(1, KeepAlive(seq), 3) is Verdict.HEARD
    assert lv.counters.beacons_missed == 2
    assert lv.receive(1, HELLO, 4) is Verdict.HEARD  # a restarted peer numbers afresh
    assert lv.receive(1, KeepAlive(1), 4) is Verdict.HEARD
    assert lv.counters.beacons_missed == 2


def test_silence_cycles_must_be_positive() -> None:
    with pytest.raises(ValueError, match="silence_cycles"):
        Liveness(MINE, 0)


def test_a_programming_cable_is_a_tool_neither_linked_nor_refused() -> None:
    """A Hello with the NO_PROGRAM digest (dh2rt flash's cable): the connector is settled
    (a trial does not wait for it), never verified, and nothing counts as refused; a module
    docked there later is verified by its own Hello."""
    lv = Liveness(MINE, SILENCE_CYCLES)
    lv.attach(1)
    lv.attach(2)
    assert lv.receive(2, Hello(MINE), 0) is Verdict.HEARD
    assert not lv.settled
    assert lv.receive(1, Hello(NO_PROGRAM), 0) is Verdict.TOOL
    assert lv.settled and not lv.verified(1) and lv.counters.refused == 0
    assert lv.receive(1, KeepAlive(1), 1) is Verdict.IGNORED  # a tool's other frames mean nothing
    assert lv.receive(1, Hello(MINE), 2) is Verdict.HEARD and lv.verified(1)
    assert lv.receive(1, Hello(OTHER), 3) is Verdict.REFUSED and lv.counters.refused == 1
