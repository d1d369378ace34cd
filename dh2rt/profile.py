"""Topology profiles: a robot's connectors, their genders, and the topological types.

A module's local topology is its ConnectorStatus: for each of its connectors, 0 when nothing
is linked there, else the index of the remote connector it is linked to (the paper's
``ConnectorStatus[x] = y``). A *profile* is data: the connector names and genders, which
status tuples are legal, and which topological type (name and the paper's T-number alias)
each legal tuple has. Several tuples may share a type.

The CONRO profile is this project's scheme; the paper's full table of types is not published.
It agrees with every example the paper gives:

* connectors ``front`` (female, active latch), ``back``, ``left``, ``right`` (male); only
  male-female links exist, so ``front`` is one of {0, back, left, right} and each of
  ``back``/``left``/``right`` is one of {0, front}: 32 local topologies;
* a snake links each module's ``back`` to the next module's ``front``; a leg hangs by its
  ``front`` from a spine module's ``left`` or ``right``;
* head T1 = (0, front, 0, 0), and a lone module (0, 0, 0, 0) is a head too, so a snake of one
  runs; tail T2 = (back, 0, 0, 0); body T16 = (back, front, 0, 0); left foot T5 =
  (left, 0, 0, 0); right foot T6 = (right, 0, 0, 0); spine types for legged robots; every
  other tuple gets a systematic name ``t_`` + one letter per connector (``0`` or the first
  letter of the remote connector), e.g. ``t_lf00``.

A profile also lists the module's *sensors* (:class:`SensorSpec`): the names a program reads
as ``S.name``, each with its unit and range. Sensor values are integers, as every DH2 value:
whatever fills a sensor (the physics stand-in, a servo driver, a ``sense`` event) rounds
to the nearest integer and clamps to the range (:meth:`SensorSpec.reading`). The CONRO
table (:data:`CONRO_SENSORS`, documented in docs/language.md, *Sensors*):

* ``roll``, ``pitch``: the module's attitude from its IMU, degrees; ``yaw``: the turn about
  the vertical its IMU's gyro integrated since the first reading, degrees, unwrapped;
* ``ir_<connector>``: distance (mm) to the nearest connector facing this one within the
  infrared pair's range and cone, 0 when none is in view (a face in contact reads 1);
  ``ir_<connector>_align``: how far (degrees) that face is from squarely facing this one,
  180 when none is in view;
* ``contact``: 1 while any part of the module touches the ground;
* ``pos1``, ``pos2``: the joints' present angles (degrees); ``load1``, ``load2``: the
  servos' present load, percent of their maximum torque, signed;
* ``docking``: 1 while a docking motion this module asked for (``reach_dock``,
  ``dock_tail_to_foot``) is under way, 0 otherwise: the motion controller's own state.
* ``floor_x``, ``floor_y`` (mm), ``floor_heading`` (degrees, counter-clockwise from the
  arena's x axis, -180..180): the overhead tracker's pose of the module's centre on the floor
  (a camera over the arena; in physics ``sim.tracker.OverheadTracker``). The docking motions
  read every module's pose from the same tracker (``firmware.motion.readings.FloorPoses``).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dh2rt.errors import TopologyError

#: Status value meaning "nothing linked at this connector".
NONE = 0


@dataclass(frozen=True, slots=True)
class TopoType:
    """A topological type: its index in the profile, name, optional T-number alias, tuples."""

    index: int
    name: str
    alias: int | None
    statuses: frozenset[tuple[int, ...]]


@dataclass(frozen=True, slots=True)
class SensorSpec:
    """A sensor of a module: its name (``S.name``), unit, and range of integer values."""

    name: str
    unit: str
    low: int
    high: int
    doc: str = ""

    def reading(self, value: float) -> int:
        """A measured value as the sensor reads it: rounded to the nearest integer (halves
        to even, as Python rounds) and clamped to the range."""
        return min(self.high, max(self.low, round(value)))

    def check(self, value: int) -> int:
        """``value`` if the sensor can read it; TopologyError naming the range otherwise."""
        if not self.low <= value <= self.high:
            raise TopologyError(f"sensor {self.name} reads {self.low}..{self.high} {self.unit}, not {value}")
        return value

    def describe(self) -> str:
        return f"{self.name} ({self.unit}, {self.low}..{self.high})"


@dataclass(frozen=True)
class Profile:
    """Connectors, genders and topological types of one kind of module.

    Connector indices start at 1 so that 0 can mean "not linked", as in the paper.
    """

    name: str
    connectors: tuple[str, ...]
    genders: tuple[str, ...]
    types: tuple[TopoType, ...]
    type_of_status: Mapping[tuple[int, ...], int] = field(repr=False)
    sensors: tuple[SensorSpec, ...] = ()

    @property
    def connector_count(self) -> int:
        return len(self.connectors)

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.sensors)

    def sensor(self, name: str) -> SensorSpec:
        """A sensor by name; TopologyError (a ValueError) naming the profile's sensors otherwise."""
        for s in self.sensors:
            if s.name == name:
                return s
        known = ", ".join(self.sensor_names) or "none"
        raise TopologyError(f"profile {self.name} has no sensor {name!r} (it has: {known})")

    def connector_index(self, name: str) -> int:
        """Index (1-based) of a connector by name; TopologyError (a ValueError) naming the
        profile's connectors for an unknown name."""
        try:
            return self.connectors.index(name) + 1
        except ValueError:
            raise TopologyError(
                f"unknown connector {name!r} (profile {self.name}: {', '.join(self.connectors)})"
            ) from None

    def connector_name(self, index: int) -> str:
        return "0" if index == NONE else self.connectors[index - 1]

    def gender(self, index: int) -> str:
        return self.genders[index - 1]

    def can_link(self, a: int, b: int) -> bool:
        """Whether connector ``a`` of one module may link to connector ``b`` of another."""
        return self.gender(a) != self.gender(b)

    def type_by_name(self, name: str) -> TopoType | None:
        """A type by name, or by its alias written ``T<number>``."""
        for t in self.types:
            if t.name == name or (t.alias is not None and name == f"T{t.alias}"):
                return t
        return None

    def type_of(self, status: Sequence[int]) -> TopoType:
        """The type of a ConnectorStatus tuple (index 0 of ``status`` is connector 1)."""
        key = tuple(status)
        try:
            return self.types[self.type_of_status[key]]
        except KeyError:
            raise TopologyError(f"status {self.describe(key)} is not legal in profile {self.name}") from None

    def describe(self, status: Sequence[int]) -> str:
        parts = (f"{c}={self.connector_name(s)}" for c, s in zip(self.connectors, status, strict=True))
        return "{" + ", ".join(parts) + "}"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Profile:
        """Build a profile from plain data (e.g. a parsed TOML table).

        ``connectors`` is a table name -> gender; ``types`` a list of tables with ``name``,
        optional ``alias`` and ``statuses`` (lists of remote connector names or "0", one entry
        per connector in declaration order). Legal tuples no type names get systematic names.
        ``sensors`` (optional) is a list of tables with ``name``, ``unit``, ``min``, ``max``
        and an optional ``doc``.
        """
        try:
            conn_table = dict(data["connectors"])
            name = str(data.get("name", "custom"))
            type_rows = list(data.get("types", []))
            sensor_rows = list(data.get("sensors", []))
        except (KeyError, TypeError) as exc:
            raise TopologyError(f"profile: missing or malformed field: {exc}") from None
        connectors = tuple(conn_table)
        genders = tuple(str(g) for g in conn_table.values())
        index = {c: i + 1 for i, c in enumerate(connectors)}

        def legal_values(i: int) -> list[int]:
            return [NONE] + [j + 1 for j in range(len(connectors)) if genders[j] != genders[i]]

        legal = list(itertools.product(*(legal_values(i) for i in range(len(connectors)))))
        legal_set = set(legal)
        types: list[TopoType] = []
        claimed: dict[tuple[int, ...], int] = {}
        for row in type_rows:
            statuses: set[tuple[int, ...]] = set()
            for raw in row["statuses"]:
                try:
                    tup = tuple(NONE if v in ("0", 0) else index[str(v)] for v in raw)
                except KeyError as exc:
                    raise TopologyError(f"profile {name}: type {row['name']}: unknown connector {exc}") from None
                if tup not in legal_set:
                    raise TopologyError(f"profile {name}: type {row['name']}: status {raw} is not legal")
                if tup in claimed:
                    raise TopologyError(f"profile {name}: status {raw} is claimed twice")
                claimed[tup] = len(types)
                statuses.add(tup)
            alias = row.get("alias")
            types.append(
                TopoType(len(types), str(row["name"]), None if alias is None else int(alias), frozenset(statuses))
            )
        for tup in legal:
            if tup not in claimed:
                letters = "".join("0" if v == NONE else connectors[v - 1][0] for v in tup)
                claimed[tup] = len(types)
                types.append(TopoType(len(types), f"t_{letters}", None, frozenset({tup})))
        return cls(name, connectors, genders, tuple(types), claimed, _sensors(name, sensor_rows))


def undeclared_sensor(name: str) -> str:
    """The message for sensing a sensor the program does not read."""
    return f"the program does not declare sensor {name} (add `sensor {name}` to read S.{name})"


def _sensors(profile: str, rows: Sequence[Any]) -> tuple[SensorSpec, ...]:
    """The sensor table of ``from_dict``; errors name the profile and the sensor."""
    specs: list[SensorSpec] = []
    for i, row in enumerate(rows):
        where = f"profile {profile}: sensor {row.get('name', i) if isinstance(row, Mapping) else i}"
        try:
            spec = SensorSpec(str(row["name"]), str(row["unit"]), row["min"], row["max"], str(row.get("doc", "")))
        except (KeyError, TypeError) as exc:
            raise TopologyError(f"{where}: missing or malformed field {exc}") from None
        if not spec.name.isidentifier():
            raise TopologyError(f"{where}: the name must be an identifier")
        if any(s.name == spec.name for s in specs):
            raise TopologyError(f"{where}: declared twice")
        bounds = (spec.low, spec.high)
        if any(not isinstance(b, int) or isinstance(b, bool) for b in bounds) or spec.low > spec.high:
            raise TopologyError(f"{where}: min and max must be whole numbers with min <= max, got {bounds}")
        specs.append(spec)
    return tuple(specs)


CONRO_DATA: dict[str, Any] = {
    "name": "conro",
    "connectors": {"front": "female", "back": "male", "left": "male", "right": "male"},
    "types": [
        {"name": "head", "alias": 1, "statuses": [["0", "front", "0", "0"], ["0", "0", "0", "0"]]},
        {"name": "tail", "alias": 2, "statuses": [["back", "0", "0", "0"]]},
        {"name": "left_foot", "alias": 5, "statuses": [["left", "0", "0", "0"]]},
        {"name": "right_foot", "alias": 6, "statuses": [["right", "0", "0", "0"]]},
        {"name": "body", "alias": 16, "statuses": [["back", "front", "0", "0"]]},
        {"name": "spine", "statuses": [["back", "front", "front", "front"]]},
        {"name": "spine_front", "statuses": [["0", "front", "front", "front"]]},
        {"name": "spine_rear", "statuses": [["back", "0", "front", "front"]]},
        {"name": "spine_lone", "statuses": [["0", "0", "front", "front"]]},
    ],
    "sensors": [
        {"name": name, "unit": unit, "min": low, "max": high, "doc": doc}
        for name, unit, low, high, doc in (
            ("roll", "deg", -180, 180, "IMU: rotation about the module's x axis, left side up > 0"),
            ("pitch", "deg", -90, 90, "IMU: rotation about the module's y axis, front end down > 0"),
            ("yaw", "deg", -720, 720, "IMU: turn about the vertical since the module's first reading, left > 0"),
            *(
                row
                for c in ("front", "back", "left", "right")
                for row in (
                    (f"ir_{c}", "mm", 0, 100, f"infrared at {c}: nearest facing connector, 0 when none in view"),
                    (f"ir_{c}_align", "deg", 0, 180, f"infrared at {c}: that face's angle off square, 180 when none"),
                )
            ),
            ("contact", "bool", 0, 1, "1 while any part of the module touches the ground"),
            ("pos1", "deg", -180, 180, "DOF1 (pitch) present angle"),
            ("pos2", "deg", -180, 180, "DOF2 (yaw) present angle"),
            ("load1", "%", -100, 100, "DOF1 servo's present load, percent of its maximum torque, signed"),
            ("load2", "%", -100, 100, "DOF2 servo's present load, percent of its maximum torque, signed"),
            ("docking", "bool", 0, 1, "1 while a docking motion this module asked for is under way"),
            ("floor_x", "mm", -10000, 10000, "overhead tracker: the module's centre on the floor, arena x"),
            ("floor_y", "mm", -10000, 10000, "overhead tracker: the module's centre on the floor, arena y"),
            ("floor_heading", "deg", -180, 180, "overhead tracker: the module's heading on the floor, left > 0"),
        )
    ],
}

#: The CONRO profile every built-in topology and example uses.
CONRO = Profile.from_dict(CONRO_DATA)
#: The CONRO module's sensors (see the module docs).
CONRO_SENSORS = CONRO.sensors
