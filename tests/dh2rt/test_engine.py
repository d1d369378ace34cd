"""One module's engine on its own (the paper's Fig. 3 loop), with no robot around it."""

from __future__ import annotations

import pytest

from dh2rt.compiler import compile_source
from dh2rt.engine import Engine
from dh2rt.errors import MissingNatives, UnknownName
from dh2rt.hormone import Arrival, Emission, Hormone
from dh2rt.profile import CONRO
from dh2rt.program import ACTIVE, PASSIVE

FRONT, BACK, LEFT, RIGHT = (CONRO.connector_index(c) for c in ("front", "back", "left", "right"))

PROGRAM = """program engine_test
const ClockCycle = 8
hormone X(p: A | B)
hormone Y
var got = 0
receptor once when T == T1 and LocalTimer == 0 { DOF1(30); emit X(A) via back }
receptor kept when T == T1 and LocalTimer == 4 { DOF2(-20); emit X(B) via back; keep_alive() }
receptor body_a when T == body and H == X(A) { V.got = V.got + 1; keep_alive() }
"""


@pytest.fixture
def engine() -> Engine:
    return Engine(compile_source(PROGRAM), timer_phase=0)


def test_one_shot_and_keep_alive(engine: Engine) -> None:
    """A receptor without keep_alive() runs once and becomes passive; one with it stays."""
    once, kept = (engine.program.receptor_index(n) for n in ("once", "kept"))
    out = engine.step()
    assert out == [Emission(BACK, Hormone("X", ("A",)))] and engine.dof == [30.0, 0.0]
    assert engine.rstatus[once] == PASSIVE
    for _ in range(7):
        engine.step()
    assert engine.timer == 0
    assert not engine.step()  # `once` is passive now: the next period sends nothing at 0
    for _ in range(3):
        engine.step()
    assert engine.step() == [Emission(BACK, Hormone("X", ("B",)))]  # LocalTimer 4, twice over
    assert engine.rstatus[kept] == ACTIVE and engine.dof == [30.0, -20.0]


def test_arrivals_set_connector_status_and_type(engine: Engine) -> None:
    """Receiving through a connector sets ConnectorStatus to the sender's connector (the
    hormone's last hop), and the topological type follows."""
    assert engine.topo_type.name == "head"
    engine.step([Arrival(FRONT, BACK, Hormone("Y"))])
    assert engine.status[FRONT - 1] == BACK
    assert engine.topo_type.name == "tail"


def test_unbound_hormones_are_forwarded_except_where_they_came_from(engine: Engine) -> None:
    engine.link_up(BACK, FRONT)
    engine.link_up(LEFT, FRONT)
    out = engine.step([Arrival(FRONT, BACK, Hormone("Y"))])
    through = sorted(e.through for e in out if e.hormone.name == "Y")
    assert through == [BACK, LEFT]
    assert all(e.hormone.path == ((BACK, FRONT),) for e in out if e.hormone.name == "Y")
    assert engine.counters["forwarded"] == 2


def test_bound_hormones_are_not_forwarded(engine: Engine) -> None:
    engine.link_up(BACK, FRONT)
    engine.step([Arrival(FRONT, BACK, Hormone("X", ("A",)))])  # body now: body_a binds it
    assert engine.topo_type.name == "body" and engine.var("got") == 1
    assert engine.counters["forwarded"] == 0


def test_send_failed_and_link_down_clear_status(engine: Engine) -> None:
    engine.link_up(BACK, FRONT)
    assert engine.topo_type.name == "head"
    engine.send_failed(BACK)
    assert engine.status[BACK - 1] == 0 and engine.counters["send_failed"] == 1
    engine.link_up(FRONT, BACK)
    engine.link_down(FRONT)
    assert engine.status == [0, 0, 0, 0]


def test_skip_equals_quiet_steps() -> None:
    program = compile_source(PROGRAM)
    a, b = Engine(program, timer_phase=1), Engine(program, timer_phase=1)
    quiet = a.quiet_cycles()
    assert quiet == 3  # timer values 1, 2, 3 have no receptor for a head
    a.skip(quiet)
    for _ in range(quiet):
        assert b.step() == ()
    assert (a.timer, a.dof, a.rstatus) == (b.timer, b.dof, b.rstatus)


def test_missing_natives_and_unknown_names() -> None:
    program = compile_source(PROGRAM.replace("var got = 0", "var got = 0\nnative zap()"))
    with pytest.raises(MissingNatives, match="zap"):
        Engine(program)
    engine = Engine(compile_source(PROGRAM))
    with pytest.raises(UnknownName, match=r"no variable 'gto' \(it has: got\)"):
        engine.var("gto")
    with pytest.raises(UnknownName, match="no sensor 'tilt'"):
        engine.set_sensor("tilt", 3)
    with pytest.raises(UnknownName, match="no receptor 'nope'"):
        engine.receptor_status("nope")
