"""Filling one module's sensors (``S.name``) each cycle, before its engine runs.

A :class:`SensorFeed` belongs to one module's runtime. It holds the module's sensor
*sources*, its *forced* values (``sense`` events) and its *pushed* readings (what the
HIL world's physics sends the module), and each cycle writes the sensors the program
declares into the engine:

* a source is anything with ``names`` (the sensors it reads) and ``read()`` returning a
  mapping name -> value in the profile's units (``drivers.base.SensorSource`` fits: the
  servos' present position and load, an IMU on I2C), or a plain callable returning such a
  mapping. Only sources that read a sensor the program declares are read at all, each every
  ``every`` cycles (at the module's own offset, so that modules sharing a bus do not all
  read in one cycle). A source whose read fails is read again after 1, 2, 4, ... up to
  ``MAX_BACKOFF`` of its turns, and at every turn again once a read succeeds: a device that
  is gone (a servo that does not answer waits out its reply timeout, 34 ms or more) costs
  the cycle loop that wait now and then, not every cycle;
* pushed readings (:meth:`SensorFeed.push`) are values someone else measured for this
  module (the HIL world's PyBullet stand-in): they are written in the next cycle;
* forced values (:meth:`SensorFeed.force`, the ``sense`` event) hold from then on: no source
  and no push overwrites them.

A program switch (a rollout) gives the feed the new engine (:meth:`SensorFeed.rebind`): the
sensors both programs declare keep their values and what ``sense`` forced, sources are read
for what the new program declares, and a sensor it declares anew that has a fixed stand-in
reading (:meth:`SensorFeed.stand_in`) gets it.

Every value goes through the profile's :class:`~dh2rt.profile.SensorSpec`: rounded to an
integer and clamped to the sensor's range. A value that is not a finite number, a name the
profile does not list, or a source that raises is a *sensor fault*: counted, logged once
per new message, and the sensor keeps its last value; the module never stops for it.
This module does no I/O of its own and imports nothing heavy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from dh2rt.engine import Engine
from dh2rt.errors import TopologyError
from dh2rt.profile import SensorSpec, undeclared_sensor

__all__ = ["MAX_BACKOFF", "SensorFeed", "SensorReader"]

#: The most turns a failing source is skipped before it is read again.
MAX_BACKOFF = 32


@runtime_checkable
class SensorReader(Protocol):
    """What the feed reads a source through (``drivers.base.SensorSource`` fits)."""

    @property
    def names(self) -> tuple[str, ...]: ...

    def read(self) -> Mapping[str, float]: ...


Source = SensorReader | Callable[[], Mapping[str, float]]


@dataclass(slots=True)
class _Source:
    label: str
    read: Callable[[], Mapping[str, float]]
    every: int
    offset: int
    #: the sensors it reads (None: a plain callable, read whatever the program declares)
    names: tuple[str, ...] | None
    #: whether it reads anything the running program declares
    active: bool = True
    #: turns to skip after the last failed read (0: none failed), and the cycle it is next read at
    backoff: int = 0
    next_read: int = 0


class SensorFeed:
    """One module's sensors: sources, pushed readings and forced values (module docs)."""

    def __init__(self, engine: Engine, *, offset: int = 0, log: Callable[[str], None] | None = None) -> None:
        self.engine = engine
        self.profile = engine.profile
        #: the engine's slot and the profile's spec of every declared sensor the profile lists
        self._slots = self._slots_of(engine)
        self.offset = offset
        self._log = log or (lambda _m: None)
        self._sources: list[_Source] = []
        self._pushed: dict[str, float] = {}
        self._stand_in: dict[str, float] = {}
        #: values ``sense`` events forced, by name: they hold until the next ``sense``
        self.forced: dict[str, int] = {}
        #: sensor faults so far (a failing read, a value that is not a number, a name not in the profile)
        self.faults = 0
        #: readings written into the engine, and readings pushed
        self.written = 0
        self.pushes = 0
        #: the last sensor fault, as ``cycle N: message`` (None: none yet)
        self.last_fault: str | None = None
        self._last_message: str | None = None

    @property
    def reading(self) -> tuple[str, ...]:
        """The labels of the sources read for the running program (those that read a sensor
        it declares)."""
        return tuple(s.label for s in self._sources if s.active) if self._slots else ()

    def _slots_of(self, engine: Engine) -> dict[str, tuple[int, SensorSpec]]:
        declared = engine.program.sensor_names
        profile = engine.profile
        return {name: (i, profile.sensor(name)) for i, name in enumerate(declared) if name in profile.sensor_names}

    # ------------------------------------------------------------ configuring

    def rebind(self, engine: Engine) -> None:
        """From now on fill ``engine`` (a program switch): the sensors it declares that the
        old one did keep their values, and their forced values hold; a forced sensor the new
        program does not declare is no longer forced."""
        old_sensors, old_slots = self.engine.sensors, self._slots
        self.engine, self.profile = engine, engine.profile
        self._slots = self._slots_of(engine)
        for name, (slot, spec) in self._slots.items():
            if name in old_slots:
                engine.sensors[slot] = old_sensors[old_slots[name][0]]
            elif name in self._stand_in:
                engine.sensors[slot] = spec.reading(self._stand_in[name])
        dropped = sorted(set(self.forced) - set(self._slots))
        for name in dropped:
            del self.forced[name]
        if dropped:
            self._log(f"sensors: the new program does not read {', '.join(dropped)}: no longer forced")
        for source in self._sources:
            source.active = source.names is None or any(n in self._slots for n in source.names)

    @property
    def declared(self) -> tuple[str, ...]:
        """The sensors this feed fills: those the program declares that the profile lists."""
        return tuple(self._slots)

    def add_source(self, source: Source, *, every: int = 1, label: str = "") -> bool:
        """Read ``source`` every ``every`` cycles from now on; False when it reads no sensor the
        program declares (it is not read while that holds: a program switch may change it). A
        source naming a sensor the profile does not list is refused (TopologyError naming it)."""
        if every < 1:
            raise ValueError(f"sensor source read every {every} cycles: must be 1 or more")
        names: tuple[str, ...] | None = None
        if isinstance(source, SensorReader):
            names = tuple(source.names)
            for name in names:
                self.profile.sensor(name)  # TopologyError naming the profile's sensors
            read = source.read
            label = label or type(source).__name__
        else:
            read = source
            label = label or getattr(source, "__name__", "sensor source")
        entry = _Source(label, read, every, self.offset % every, names)
        entry.active = names is None or any(n in self._slots for n in names)
        self._sources.append(entry)
        return entry.active

    def force(self, name: str, value: int) -> None:
        """Sensor ``name`` reads ``value`` from now on (a ``sense`` event): TopologyError if the
        profile has no such sensor, the value is out of its range, or the program does not
        declare it."""
        spec = self.profile.sensor(name)
        spec.check(value)
        if name not in self._slots:
            raise TopologyError(undeclared_sensor(name))
        self.forced[name] = value
        self.engine.sensors[self._slots[name][0]] = value

    def push(self, values: Mapping[str, float]) -> None:
        """Readings measured elsewhere for this module; written at the next :meth:`fill`."""
        self._pushed.update(values)
        self.pushes += 1

    def stand_in(self, values: Mapping[str, float]) -> None:
        """Fixed readings of sensors with no device (``[sensors] stand_in``): written at the
        next :meth:`fill`, and again for a sensor a switched-to program declares anew."""
        self._stand_in.update(values)
        self.push(values)

    # ------------------------------------------------------------ each cycle

    def fill(self, cycle: int) -> None:
        """Write this cycle's readings into the engine (before it runs)."""
        if not self._slots:
            self._pushed.clear()
            return
        if self._pushed:
            pushed, self._pushed = self._pushed, {}
            self._write(pushed, "pushed readings", cycle)
        for source in self._sources:
            if not source.active or cycle % source.every != source.offset or cycle < source.next_read:
                continue
            try:
                values = source.read()
            except Exception as exc:  # any failing device: a counted, logged fault, never a crash
                self._fault(cycle, f"{source.label}: {type(exc).__name__}: {exc}")
                source.backoff = min(MAX_BACKOFF, 2 * source.backoff or 1)
                source.next_read = cycle + (source.backoff + 1) * source.every
                continue
            source.backoff = 0
            self._write(values, source.label, cycle)

    def _write(self, values: Mapping[str, float], label: str, cycle: int) -> None:
        sensors = self.engine.sensors
        forced = self.forced
        for name, value in values.items():
            slot = self._slots.get(name)
            if slot is None:
                if name not in self.profile.sensor_names:
                    self._fault(cycle, f"{label}: no sensor {name!r} in profile {self.profile.name}")
                continue  # the program does not read it
            if name in forced:
                continue
            if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
                self._fault(cycle, f"{label}: sensor {name} read {value!r}, not a number: kept its last value")
                continue
            sensors[slot[0]] = slot[1].reading(value)
            self.written += 1

    def _fault(self, cycle: int, message: str) -> None:
        self.faults += 1
        self.last_fault = f"cycle {cycle}: {message}"
        if message != self._last_message:
            self._log(f"sensor fault: {message}")
            self._last_message = message
