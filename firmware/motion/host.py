"""A module's docking motions, whoever runs the module (sans-IO): the one place that decides
what a module does with the motion frames it receives, the docking natives its program
calls, and the SET_OFF that makes it a released foot.

:class:`MotionHost` holds the module's three parts of a docking:

- its :class:`firmware.motion.member.Member` (it answers ASKs, holds TARGETS, passes frames on);
- the reach it runs as the asking module (``reach_dock``: :class:`firmware.motion.asking.SelfReach`;
  ``reach_and_dock``: :class:`firmware.motion.assimilating.SelfAssimilate`), one at a time;
- its own trip and creep once a SET_OFF made it the foot of another module's
  ``reach_and_dock`` (:class:`firmware.motion.foot.Foot`).

Its owner gives it the frames that came (:meth:`MotionHost.received`), the docking effects the
program asked (:meth:`MotionHost.start`) and, once a cycle before the engine runs,
:meth:`MotionHost.before_cycle`; it sends the frames those return through their connectors,
writes :attr:`MotionHost.joints` to the servos in place of the program's (empty: the
program's), and reports :attr:`MotionHost.effects` (``release``, ``foot``, ``reach_ended``) to
its world. The module process (``firmware.main_loop.ModuleHost``) owns one per module; so does
the physics runner with the motions in the modules (``sim.module_motions``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from dh2rt.profile import Profile
from firmware.motion.asker import Asker
from firmware.motion.member import Body, Member
from firmware.outbound import Out

if TYPE_CHECKING:  # the planner (numpy) is loaded by the first reach or trip, not at every boot
    from firmware.motion.asking import LatchAsk, OwnSenses, SelfReach
    from firmware.motion.assimilating import SelfAssimilate
    from firmware.motion.body import ConroModel
    from firmware.motion.foot import Foot

#: The docking natives a module carries out itself.
NATIVES = ("reach_dock", "reach_and_dock")


class MotionHost:
    """One module's docking motions (module docs)."""

    def __init__(
        self,
        module: int,
        profile: Profile,
        body: Body,
        senses: OwnSenses,
        latch: LatchAsk,
        log: Callable[[str], None],
        *,
        model: ConroModel | None = None,
    ) -> None:
        self.module = module
        self.profile = profile
        self.senses = senses
        self.latch = latch
        self.log = log
        self._model = model
        self.body = body
        self.member = Member(module, body, log=log, attitude=lambda: senses.attitude().get(module))
        #: the reach this module runs (the last one, done or not), and how many motion ids it used
        self.reach: SelfReach | SelfAssimilate | None = None
        self.motions = 0
        #: this module's own trip and creep once it is the released foot of a reach_and_dock
        self.foot: Foot | None = None
        #: what this module's own reach or trip holds on its joints (DOF index -> degrees)
        self.own: dict[int, float] = {}
        #: what to report to the world since the owner last took them: (kind, args)
        self.effects: list[tuple[str, list[Any]]] = []

    @property
    def model(self) -> ConroModel:
        """The body the motions plan with (loaded with the planner, at the first use)."""
        if self._model is None:
            from firmware.motion.body import DEFAULT_MODEL

            self._model = DEFAULT_MODEL
        return self._model

    @property
    def joints(self) -> dict[int, float]:
        """What the module's servos hold this cycle in place of its program's: its own reach's
        or trip's targets, else a chain's it is a member of (empty: the program's)."""
        return self.own or self.member.held

    @property
    def busy(self) -> bool:
        """A reach of its own or a trip is under way."""
        return (self.reach is not None and not self.reach.done) or (self.foot is not None and not self.foot.done)

    def received(self, connector: int, payload: bytes, cycle: int) -> list[Out]:
        """A motion frame came in at ``connector``: what to send on or answer."""
        return self.member.received(connector, payload, cycle)

    def _next_motion(self) -> int:
        """A new motion id: the module's index in it, so that two askers' motions never share
        one at a member."""
        motion = (self.module & 0xFF) << 8 | (self.motions & 0xFF)
        self.motions += 1
        return motion

    # ------------------------------------------------------------ the natives

    def start(self, kind: str, args: Sequence[Any], links: Sequence[int], cycle: int) -> None:
        """The program asked ``kind`` (one of :data:`NATIVES`) this cycle with ``args``;
        ``links`` are the module's links now (its ConnectorStatus)."""
        if self.reach is not None and not self.reach.done:
            self.log(f"{kind}: a reach of this module is under way; this one refused")
            return
        try:
            if kind == "reach_and_dock":
                self.reach = self._assimilating(args, links, cycle)
            else:
                from firmware.motion.asking import SelfReach

                connector, route, target = int(args[0]), tuple(int(c) for c in args[1]), int(args[2])
                asker = Asker(self._next_motion(), self.module, tuple(links), route, cycle, log=self.log)
                self.reach = SelfReach(
                    asker, connector, target, self.senses, self.latch, self.model, self.profile, self.log
                )
                name = self.profile.connector_name(connector)
                self.log(f"reach_dock: motion {asker.motion} from {name}, learning the chain")
        except (IndexError, TypeError, ValueError) as exc:
            self.log(f"{kind} {list(args)!r} refused: {exc}")

    def _assimilating(self, args: Sequence[Any], links: Sequence[int], cycle: int) -> SelfAssimilate:
        """``reach_and_dock(connector, route)``: the foot at the route's end comes to this
        module's connector by its own trip (the asking side)."""
        from firmware.motion.assimilating import MAX_BODY, SelfAssimilate

        front = self.profile.connector_index("front")
        links = tuple(links)
        connector, route = int(args[0]), tuple(int(c) for c in args[1])
        to_foot = Asker(self._next_motion(), self.module, links, route, cycle, log=self.log)
        body = None
        if links[front - 1]:  # up the robot by front links, as far as they go
            body = Asker(self._next_motion(), self.module, links, (front,) * MAX_BODY, cycle, log=self.log)
        self.log(
            f"reach_and_dock: motion {to_foot.motion} from {self.profile.connector_name(connector)}, learning the route"
        )
        return SelfAssimilate(
            to_foot,
            body,
            connector,
            self.senses,
            self.latch,
            self.model,
            self.profile,
            self.log,
            own_links=self.body.links,
            next_motion=self._next_motion,
        )

    # ------------------------------------------------------------ each cycle

    def before_cycle(self, cycle: int) -> list[Out]:
        """Just before the module's cycle: a chain gone silent gives the joints back; the
        reach it runs and the foot it is make their steps. The frames to send."""
        if self.member.holding is not None:
            self.member.cycle(cycle)
        out = self._step_reach(cycle)
        self._step_foot()
        return out

    def _step_reach(self, cycle: int) -> list[Out]:
        reports, self.member.reports = self.member.reports, []
        reach = self.reach
        if reach is None or reach.done:
            return []
        for report in reports:
            reach.received(report, cycle)
        out = reach.step(cycle)
        self.effects.extend(reach.effects)  # its own module's part: a release of its face
        reach.effects.clear()
        self.own = dict(reach.own_targets)
        if reach.done:
            self.effects.append(("reach_ended", [reach.connector, reach.verdict]))
        return out

    def _step_foot(self) -> None:
        """A SET_OFF this module took makes it the foot of a ``reach_and_dock``: it lets go of
        its front (a ``release`` effect), then walks and creeps on its own joints by the
        tracker and its front infrared; what becomes of it goes out as ``foot`` effects."""
        set_off, self.member.set_off = self.member.set_off, None
        front = self.profile.connector_index("front")
        # the asker sends it each cycle until the foot lets go: a copy of the motion this foot
        # runs or ran is not a new trip
        if set_off is not None and (self.foot is None or self.foot.set_off.motion != set_off.motion):
            from firmware.motion.foot import Foot

            self.foot = Foot(self.module, set_off, model=self.model)
            self.effects.append(("foot", ["set_off", f"motion {set_off.motion}, to module {set_off.target}"]))
            self.effects.append(("release", [front]))
            self.log(f"foot: motion {set_off.motion}: letting go, to module {set_off.target}")
        foot = self.foot
        if foot is None or foot.done:
            if self.reach is None or self.reach.done:
                self.own = {}
            return
        targets = foot.step(self.senses.floor(), self.senses.infrared(), self.body.links()[front - 1] != 0)
        self.effects.extend(("foot", [kind, detail]) for kind, detail in foot.events)
        foot.events.clear()
        self.own = targets
