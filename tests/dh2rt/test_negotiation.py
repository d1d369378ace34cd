"""Link negotiation (dh2rt.negotiation) in a simulated robot: many negotiators, one bus
(tests/dh2rt/negotiation_sim.py says what the harness models).

Every property is swept over seeds and over the timing of the contacts (which step each dock
is made, how late each side senses it, how late messages arrive). The messages' codec is
tested in tests/wire/test_negotiation.py.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import Any

import pytest

from dh2rt.errors import DecodeError
from dh2rt.negotiation import Attach, LinkNegotiator, LinkState, SendBus, SendLocal
from dh2rt.wire.can_frames import MAX_LINK_ID
from dh2rt.wire.negotiation import (
    FIRST_LINK_ID,
    LAST_LINK_ID,
    MANAGEMENT_ID,
    BusMessage,
    BusOp,
    LocalType,
    Offer,
    decode_bus,
    decode_local,
    encode_bus,
    encode_sealed,
)
from tests.dh2rt.negotiation_sim import (
    DT,
    Dock,
    Rigged,
    World,
    branching,
    leader_end,
    pairs,
    snake,
    timing,
)

SEEDS = range(6)
REANNOUNCE_STEPS = round(1.0 / DT)  # the default reannounce_s in steps
#: Few ids to pick from, so that a stale id picked again would not go unnoticed.
SMALL_POOL = (1, 4)
#: Delivery timings: everything arrives the next step; or bus frames up to 1 step and CLC
#: messages up to 2 steps later, with the claim window grown by the bus round trip's slack.
LATENESS = [
    pytest.param({}, id="prompt"),
    pytest.param({"bus_jitter": 1, "clc_jitter": 2, "claim_ticks": 4}, id="late"),
]


# ---------------------------------------------------------------------------------------------
# The negotiator's own checks


@pytest.mark.parametrize(
    "kwargs",
    [
        {"connectors": []},
        {"connectors": [1, 1]},
        {"connectors": [0]},
        {"claim_ticks": 1},
        {"retry_ticks": 0},
        {"timeout_ticks": 5},
        {"reannounce_s": 4.0},
        {"leader_silence_s": 6.0},
        {"quarantine_s": -1.0},
        {"link_ids": (0, 10)},
        {"link_ids": (10, 9)},
        {"link_ids": (1, MAX_LINK_ID)},
    ],
)
def test_bad_settings_are_refused(kwargs: dict[str, object]) -> None:
    args: dict[str, object] = {"connectors": [1, 2], "rng": random.Random(0)}
    args.update(kwargs)
    with pytest.raises(ValueError):
        LinkNegotiator(**args)  # type: ignore[arg-type]


def test_unknown_connector_is_refused() -> None:
    neg = LinkNegotiator([1, 2], random.Random(0))
    with pytest.raises(ValueError, match="connector 3"):
        neg.contact(3, True)


def test_a_lone_contact_offers_every_cycle_and_never_attaches() -> None:
    """Touching something that does not answer: the same OFFER each cycle, nothing else."""
    neg = LinkNegotiator([1], random.Random(0))
    actions = neg.contact(1, True)
    for n in range(1, 50):
        actions += neg.tick(n * DT)
    sent = [a.data for a in actions if isinstance(a, SendLocal) and a.connector == 1]
    assert len(sent) == len(actions) == 49  # at contact, then one per cycle after the contact's
    assert len(set(sent)) == 1 and isinstance(decode_local(sent[0]), Offer)
    assert neg.state(1) is LinkState.OFFERING and not neg.links


def test_a_bus_action_is_a_management_frame() -> None:
    assert SendBus(encode_bus(BusMessage(BusOp.CLAIM, 5, 9))).frame.arbitration_id == MANAGEMENT_ID


# ---------------------------------------------------------------------------------------------
# Two modules


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("skew", [0, 1, 4])
def test_two_modules_dock_and_agree(seed: int, skew: int) -> None:
    world = World(seed, echo=seed % 2 == 1)
    a, b = world.add("a"), world.add("b")
    dock = world.dock("a", 2, "b", 1, at=3 + seed, skew=skew)
    world.run_until(lambda: world.link_id(dock) is not None, limit=3 + seed + skew + 12)
    link_id = world.link_id(dock)
    assert link_id is not None and FIRST_LINK_ID <= link_id <= LAST_LINK_ID
    assert {a.attached[2].side, b.attached[1].side} == {0, 1}
    world.run(3 * REANNOUNCE_STEPS + 5)  # and it stays so, re-announced
    assert world.link_id(dock) == link_id
    assert [type(x) for _, x in a.history] == [Attach] and [type(x) for _, x in b.history] == [Attach]
    leader = leader_end(world, dock)[0]
    claims = world.sent(BusOp.CLAIM)
    assert len(claims) == 3 and {name for _, name, _ in claims} == {leader}
    assert len(world.sent(BusOp.HOLD)) == 3  # one a second, only from the leader
    assert not world.sent(BusOp.RELEASE)
    assert a.neg.counters.negotiations == b.neg.counters.negotiations == 1
    assert a.neg.links == {2: a.attached[2]} and b.neg.links == {1: b.attached[1]}
    assert not world.violations


def test_a_nonce_tie_is_redrawn() -> None:
    world = World(0)
    ra = Rigged("tie/a", nonces=[0x1234_5678])
    rb = Rigged("tie/b", nonces=[0x1234_5678])
    world.add("a", rng=ra)
    world.add("b", rng=rb)
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(lambda: world.link_id(dock) is not None, limit=20)
    assert ra.nonce_draws == rb.nonce_draws == 2


# ---------------------------------------------------------------------------------------------
# Many docks on one bus


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random"])
@pytest.mark.parametrize("late", LATENESS)
def test_twenty_pairs_get_distinct_links(seed: int, when: str, late: dict[str, Any]) -> None:
    world = World(seed, echo=True, **late)
    docks = pairs(world, 20, at=timing(when, seed))
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("late", LATENESS)
def test_twenty_pairs_drawing_the_same_id_at_once(seed: int, late: dict[str, Any]) -> None:
    """Every leader's first candidate is 4242: one pair keeps it, the 19 others lose the
    claim and pick again; no two pairs are ever attached to one id."""
    world = World(seed, **late)
    for i in range(20):
        for side in "ab":
            world.add(f"p{i}{side}", rng=Rigged(f"{seed}/p{i}{side}", picks=[4242]))
    docks = [world.dock(f"p{i}a", 2, f"p{i}b", 1, at=3) for i in range(20)]
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert [world.link_id(d) for d in docks].count(4242) == 1
    totals = world.counters()
    # 19 pairs gave 4242 up: in a claim contest, or (when late messages spread the claims out)
    # before claiming, having heard another pair's claim
    assert totals.collisions + totals.repicks >= 19
    assert totals.collisions >= (19 if not late else 1)
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random"])
def test_twenty_pairs_share_a_pool_of_twenty_ids(seed: int, when: str) -> None:
    """With exactly 20 ids to go round, every id ends up used once: collisions are the norm."""
    world = World(seed, link_ids=(1, 20))
    docks = pairs(world, 20, at=timing(when, seed))
    world.run_until(world.settled, limit=400)
    assert sorted(world.link_id(d) or 0 for d in docks) == list(range(1, 21))
    totals = world.counters()
    assert totals.collisions > 0 if when == "together" else totals.collisions + totals.repicks > 0
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_a_snake_of_21_docking_at_once(seed: int) -> None:
    world = World(seed)
    docks = snake(world, 21, at=lambda i: 4)
    world.run_until(world.settled, limit=60)
    assert len({world.link_id(d) for d in docks}) == 20
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("when", ["together", "random", "sequential"])
@pytest.mark.parametrize("shape", [snake, branching], ids=["snake8", "branching"])
@pytest.mark.parametrize("late", LATENESS)
def test_robots_link_up(seed: int, when: str, shape: Callable[..., list[Dock]], late: dict[str, Any]) -> None:
    world = World(seed, **late)
    docks = shape(world, 8, at=timing(when, seed)) if shape is snake else shape(world, at=timing(when, seed))
    world.run_until(world.settled, limit=80)
    if shape is branching:
        assert len(world.nodes["hub"].attached) == 4
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()
    assert all(len(n.history) == len(n.attached) for n in world.nodes.values()), "a link was dropped"
    assert len(docks) == len({world.link_id(d) for d in docks})
    assert not world.violations


# ---------------------------------------------------------------------------------------------
# Collisions between established pairs


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("phase", [0, 17, 49])
def test_two_established_pairs_on_one_id_are_separated(seed: int, phase: int) -> None:
    """Two pairs establish id 77 on two separate buses; the buses are joined (two robots
    docking together). Within one re-announce period one pair yields; the other never
    detaches."""
    world = World(seed)
    for i, partition in ((0, 1), (1, 2)):
        for side in "ab":
            world.add(f"p{i}{side}", rng=Rigged(f"{seed}/p{i}{side}", picks=[77])).partition = partition
    docks = [world.dock(f"p{i}a", 2, f"p{i}b", 1, at=2 + 5 * i) for i in range(2)]
    world.run_until(lambda: all(world.link_id(d) == 77 for d in docks), limit=30)
    world.run(phase)
    joined = world.step_no
    for node in world.nodes.values():
        node.partition = 0
    world.run_until(lambda: world.link_id(docks[0]) != world.link_id(docks[1]), limit=REANNOUNCE_STEPS + 3)
    world.run_until(world.settled, limit=20)
    winner, loser = (docks[0], docks[1]) if world.link_id(docks[0]) == 77 else (docks[1], docks[0])
    assert world.link_id(loser) not in (None, 77)
    for end in (winner.a, winner.b):
        assert world.nodes[end[0]].detaches(end[1]) == [], "the winner was disturbed"
    for end in (loser.a, loser.b):
        assert len(world.nodes[end[0]].detaches(end[1], since=joined)) == 1
    assert world.counters().collisions == 1
    assert all(step < joined + REANNOUNCE_STEPS + 3 for step, *_ in world.violations)


@pytest.mark.parametrize("seed", SEEDS)
def test_an_injected_hold_with_a_lower_tag_takes_the_id(seed: int) -> None:
    """A forged HOLD for our id with the lowest tag there is: both ends yield at once and the
    pair moves to a fresh id."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    assert old is not None
    world.broadcast(encode_bus(BusMessage(BusOp.HOLD, old, 1)))
    world.step()
    world.step()
    assert world.link_id(dock) is None and not any(n.attached for n in world.nodes.values())
    world.run_until(world.settled, limit=15)
    assert world.link_id(dock) != old
    assert world.counters().collisions == 1


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("later", [1, 20, 45])
@pytest.mark.parametrize("late", LATENESS)
def test_newcomers_claiming_a_held_id_yield(seed: int, later: int, late: dict[str, Any]) -> None:
    """Two modules that started after the last HOLD (so they know nothing of the bus) dock
    ``later`` steps after a pair established an id, and their leader tries that very id: the
    owners' HOLD beats the claim, the newcomers pick again, the owners never notice."""
    world = World(seed, **late)
    world.add("a")
    world.add("b")
    owners = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    held = world.link_id(owners)
    assert held is not None
    world.run(later)
    for name in ("c", "d"):
        world.add(name, rng=Rigged(f"{seed}/{name}", picks=[held]))
    newcomers = world.dock("c", 1, "d", 1, at=world.step_no)
    world.run_until(world.settled, limit=25)
    assert world.link_id(owners) == held and world.link_id(newcomers) != held
    assert len(world.nodes["a"].history) == len(world.nodes["b"].history) == 1
    totals = world.counters()
    if later < REANNOUNCE_STEPS - 5:  # no HOLD in between: they could only learn of it by claiming
        assert totals.collisions == 1 and totals.defences >= 1
    else:  # a re-announce may come first: then they never propose or never claim it
        assert totals.collisions <= 1 and (totals.collisions == 0) == (totals.defences == 0)
    assert not world.violations


@pytest.mark.parametrize("claim_ticks", [2, 4])
def test_the_claim_window_must_cover_the_bus_round_trip(claim_ticks: int) -> None:
    """With bus frames up to a step late, a claim's round trip (claim -> owner's next cycle ->
    HOLD -> claimer's next cycle) takes up to 4 cycles: a 2-cycle window lets newcomers
    conclude before the owners' defence arrives (two pairs on one id), a 4-cycle one never."""
    unsafe = 0
    for seed in range(12):
        world = World(seed, bus_jitter=1, claim_ticks=claim_ticks)
        world.add("a")
        world.add("b")
        owners = world.dock("a", 1, "b", 1, at=1)
        world.run_until(world.settled, limit=20)
        for name in ("c", "d"):
            world.add(name, rng=Rigged(f"{seed}/{name}", picks=[world.link_id(owners) or 0]))
        world.dock("c", 1, "d", 1, at=world.step_no)
        world.run_until(world.settled, limit=4 * REANNOUNCE_STEPS)
        unsafe += bool(world.violations)
    assert (unsafe > 0) == (claim_ticks == 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_hold_only_the_follower_heard(seed: int) -> None:
    """A rival HOLD reaches the follower but not the leader (its receive queue overflowed):
    the follower yields and waits for a new PROPOSE that never comes; after ``timeout_ticks``
    it starts over, the leader sees the new OFFER, releases the id, and the pair relinks."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    assert old is not None
    follower = dock.other(leader_end(world, dock))
    world.broadcast(encode_bus(BusMessage(BusOp.HOLD, old, 1)), only=[follower[0]])
    world.step()
    world.step()
    assert follower[1] not in world.nodes[follower[0]].attached
    timeout = world.nodes[follower[0]].neg.timeout_ticks
    world.run(timeout - 2)
    assert world.link_id(dock) is None  # still waiting
    world.run_until(world.settled, limit=15)
    assert world.link_id(dock) != old and world.counters().resets >= 2


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("op", [BusOp.CLAIM, BusOp.HOLD])
def test_an_injected_rival_that_should_lose_is_answered(seed: int, op: BusOp) -> None:
    """A rival CLAIM (any tag: established beats claiming) or a rival HOLD with the highest
    tag: both ends answer with a HOLD at once and keep the link."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    link_id = world.link_id(dock)
    assert link_id is not None
    tag = 1 if op is BusOp.CLAIM else 0xFFFF_FFFF
    injected = world.step_no
    world.broadcast(encode_bus(BusMessage(op, link_id, tag)))
    world.run(2)
    holds = world.sent(BusOp.HOLD, link_id, since=injected)
    assert {name for _, name, _ in holds} == {"a", "b"}
    assert world.counters().defences == 2
    assert world.link_id(dock) == link_id and all(len(n.history) == 1 for n in world.nodes.values())


# ---------------------------------------------------------------------------------------------
# Undock, re-dock, restart


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("skew", [0, 3])
@pytest.mark.parametrize("away", [1, 10, 200])
@pytest.mark.parametrize("late", LATENESS)
def test_undock_releases_and_redock_gets_a_fresh_id(seed: int, skew: int, away: int, late: dict[str, Any]) -> None:
    world = World(seed, link_ids=SMALL_POOL, **late)  # a re-used id would show in one seed of four
    world.add("a")
    world.add("b")
    dock = world.dock("a", 3, "b", 4, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    apart = world.step_no + 5
    world.undock(dock, at=apart, skew=skew)
    world.run(5 + skew + 1)
    assert not any(n.attached for n in world.nodes.values())
    # the first to sense it releases; the other hears that (with skew 0 both send one)
    assert {name for _, name, _ in world.sent(BusOp.RELEASE, old)} == ({"a", "b"} if skew == 0 else {"a"})
    assert world.nodes["a"].detaches(3) and world.nodes["b"].detaches(4)
    assert all(old in n.neg.ids_quarantined for n in world.nodes.values())
    world.redock(dock, at=apart + away)
    world.run_until(lambda: world.link_id(dock) is not None, limit=away + 20)
    assert world.link_id(dock) != old
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("newcomer_leads", [False, True])
def test_a_newcomer_never_gets_a_released_id(seed: int, newcomer_leads: bool) -> None:
    """``b`` undocks from ``a`` and docks with ``c``, which started after the RELEASE and knows
    nothing of it, and whose leader is forced to try the released id first. If ``b`` leads, its
    own quarantine keeps it off that id; if ``c`` leads, ``b`` REJECTs it."""
    world = World(seed, link_ids=SMALL_POOL)
    world.add("a")
    rb = Rigged(f"{seed}/b")
    world.add("b", rng=rb)
    first = world.dock("a", 2, "b", 1, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(first)
    assert old is not None
    world.undock(first, at=world.step_no + 1)
    world.run(3)
    rc = Rigged(f"{seed}/c", nonces=[0xFFFF_FFFF if newcomer_leads else 0], picks=[old])
    rb.picks = [old]
    world.add("c", rng=rc)
    second = world.dock("b", 1, "c", 2, at=world.step_no + 1)
    world.run_until(world.settled, limit=20)
    assert world.link_id(second) not in (None, old)
    assert (leader_end(world, second)[0] == "c") == newcomer_leads
    assert world.counters().repicks == (1 if newcomer_leads else 0)  # the REJECT
    assert (not rc.picks, not rb.picks) == (newcomer_leads, not newcomer_leads)  # the leader's forced pick was drawn


@pytest.mark.parametrize("seed", SEEDS)
def test_undocking_one_link_leaves_the_others_alone(seed: int) -> None:
    world = World(seed)
    docks = snake(world, 5, at=timing("random", seed))
    world.run_until(world.settled, limit=80)
    before = {d: world.link_id(d) for d in docks}
    world.undock(docks[1], at=world.step_no + 1, skew=1)
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()  # docks[1] is no longer made
    assert all(world.link_id(d) == before[d] for d in docks if d is not docks[1])
    assert world.link_id(docks[1]) is None
    assert sum(len(n.detaches()) for n in world.nodes.values()) == 2


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("missed_by", [0, 1])
def test_a_bounce_one_side_missed(seed: int, missed_by: int) -> None:
    """The connectors part and touch again two cycles later; one side never sensed it. The side
    that did releases the link and offers again; the other, still established, hears its link
    released (or the new OFFER) and starts over."""
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 2, at=2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    at = world.step_no + 3
    saw = dock.b if missed_by == 0 else dock.a
    world.at(at, lambda: setattr(dock, "made", False))
    world.sense(saw, False, at)
    world.at(at + 2, lambda: setattr(dock, "made", True))
    world.sense(saw, True, at + 2)
    world.run_until(lambda: world.settled(), limit=40)
    assert world.link_id(dock) != old
    missed = dock.other(saw)
    assert len(world.nodes[missed[0]].detaches(missed[1])) == 1
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("who", ["leader", "follower"])
@pytest.mark.parametrize("down", [0, 5, 300])
@pytest.mark.parametrize("late", LATENESS)
def test_a_module_killed_and_restarted_rejoins(seed: int, who: str, down: int, late: dict[str, Any]) -> None:
    """The module's process dies (no release) and a fresh one starts ``down`` steps later with
    the contact still made: it rejoins with a fresh id, the neighbour dropped the old one. A
    bystander pair on the same bus is never disturbed."""
    world = World(seed, link_ids=SMALL_POOL, **late)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 2, "b", 1, at=2)
    bystanders = pairs(world, 1, at=lambda i: 4)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    leader = leader_end(world, dock)
    victim = leader if who == "leader" else dock.other(leader)
    neighbour = dock.other(victim)
    killed = world.step_no
    world.kill(victim[0])
    world.run(down)
    if down * DT > 3.5 + 2 * DT and who == "leader":  # the follower gave up on its silent leader
        (gave_up,) = world.nodes[neighbour[0]].detaches(neighbour[1])
        assert killed < gave_up <= killed + round(3.5 / DT) + 2
        assert world.sent(BusOp.RELEASE, old)
    world.restart(victim[0])
    world.run_until(world.settled, limit=40)  # a restarted leader knows nothing: it may be REJECTed
    assert world.link_id(dock) != old
    assert len(world.nodes[neighbour[0]].detaches(neighbour[1])) == 1
    assert len(world.nodes[bystanders[0].a[0]].history) == 1
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_the_hub_of_a_branching_robot_restarts(seed: int) -> None:
    world = World(seed, link_ids=(1, 10))  # 4 released, 1 in use: the hub must avoid 5 of 10
    docks = branching(world, at=timing("random", seed))
    world.run_until(world.settled, limit=80)
    old = {d: world.link_id(d) for d in docks}
    world.kill("hub")
    world.run(7)
    world.restart("hub")
    world.run_until(world.settled, limit=30)
    for d in docks:
        assert (world.link_id(d) != old[d]) == ("hub" in (d.a[0], d.b[0]))
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_a_follower_lets_go_of_a_dead_leader_before_the_id_ages_out(seed: int) -> None:
    world = World(seed)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 2, "b", 1, at=2)
    pairs(world, 1, at=lambda i: 2)
    world.run_until(world.settled, limit=20)
    old = world.link_id(dock)
    leader = leader_end(world, dock)
    follower = dock.other(leader)
    world.kill(leader[0])
    dead = world.step_no
    world.run(round(3.5 / DT) + 2)
    assert world.nodes[follower[0]].detaches(follower[1]), "the follower still holds the id"
    assert world.nodes[follower[0]].neg.state(follower[1]) is LinkState.OFFERING
    bystander = world.nodes["p0a"].neg
    assert old not in bystander.ids_in_use and old in bystander.ids_quarantined
    assert world.sent(BusOp.RELEASE, old, since=dead)[0][1] == follower[0]


@pytest.mark.parametrize("seed", SEEDS)
def test_shutdown_releases_every_link(seed: int) -> None:
    world = World(seed)
    docks = branching(world)
    world.run_until(world.settled, limit=40)
    hub = world.nodes["hub"]
    world.apply(hub, hub.neg.shutdown())
    world.kill("hub")
    assert len(world.sent(BusOp.RELEASE)) == 4
    world.run(3)
    for d in docks[:4]:  # the hub's four links: the far ends heard them released
        end = d.b if d.a[0] == "hub" else d.a
        assert world.nodes[end[0]].neg.state(end[1]) is LinkState.OFFERING
        assert end[1] not in world.nodes[end[0]].attached
    assert world.link_id(docks[4]) is not None  # back-tail never involved


def test_ids_nobody_announces_age_out() -> None:
    neg = LinkNegotiator([1], random.Random(0))
    neg.tick(0.0)
    neg.bus_received(encode_bus(BusMessage(BusOp.CLAIM, 99, 5)))
    neg.bus_received(encode_bus(BusMessage(BusOp.RELEASE, 98, 5)))
    assert neg.ids_in_use == {99} and neg.ids_quarantined == {98}
    neg.tick(4.9)
    assert neg.ids_in_use == {99}
    neg.tick(5.1)
    assert neg.ids_in_use == frozenset() and neg.ids_quarantined == {98}
    neg.tick(10.1)
    assert neg.ids_quarantined == frozenset()


# ---------------------------------------------------------------------------------------------
# A lossy, garbling channel and garbage


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize(("loss", "garble"), [(0.3, 0.0), (0.0, 0.2), (0.3, 0.1)])
@pytest.mark.parametrize("late", LATENESS)
def test_a_lossy_garbling_channel_still_converges(seed: int, loss: float, garble: float, late: dict[str, Any]) -> None:
    world = World(seed, loss=loss, garble=garble, **late)
    docks = snake(world, 8, at=timing("random", seed))
    world.run_until(world.settled, limit=600)
    settled = world.step_no
    world.run(2 * REANNOUNCE_STEPS)
    assert world.all_linked()
    assert all(not n.detaches(since=settled) for n in world.nodes.values())
    assert len({world.link_id(d) for d in docks}) == 7
    totals = world.counters()
    if loss:
        assert totals.retries > 0
    if garble:
        assert totals.garbage + totals.stale > 0
    assert not world.violations


@pytest.mark.parametrize("seed", SEEDS)
def test_garbage_is_counted_and_ignored(seed: int) -> None:
    """Random bytes on the bus and on every CLC, in every phase of a negotiation: counted as
    garbage (or stale, for well-formed messages under no tag of ours), never raised, and the
    links come out as without them."""
    rng = random.Random(f"garbage/{seed}")
    world = World(seed)
    docks = snake(world, 4, at=timing("random", seed))
    undecodable = 0
    while not world.all_linked() or world.step_no < 60:
        for node in world.nodes.values():
            for c in (1, 2, 3, 4):
                data = rng.randbytes(rng.choice([0, 3, 7, 8, 8, 8, 9]))
                undecodable += _undecodable(decode_local, data)
                world.apply(node, node.neg.local_received(c, data))
            data = rng.randbytes(rng.choice([0, 8, 8, 12]))
            undecodable += _undecodable(decode_bus, data)
            world.apply(node, node.neg.bus_received(data))
        world.step()
        assert world.step_no < 200
    assert world.counters().garbage == undecodable > 0
    assert len({world.link_id(d) for d in docks}) == 3
    assert not world.violations


def _undecodable(decode: Callable[[bytes], object], data: bytes) -> int:
    try:
        decode(data)
    except DecodeError:
        return 1
    return 0


def test_messages_from_another_negotiation_are_stale() -> None:
    world = World(0)
    world.add("a")
    world.add("b")
    dock = world.dock("a", 1, "b", 1, at=1)
    world.run_until(world.settled, limit=20)
    link_id = world.link_id(dock)
    assert link_id is not None
    for kind in (LocalType.PROPOSE, LocalType.ACCEPT, LocalType.CONFIRM, LocalType.REJECT):
        for node in world.nodes.values():
            assert node.neg.local_received(1, encode_sealed(kind, link_id ^ 1, 0x5EA1)) == []
    world.run(5)
    assert world.counters().stale == 8 and world.link_id(dock) == link_id
