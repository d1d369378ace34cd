"""The module's latch from its config (module.toml ``[latch]``): the seam a dock uses.

:func:`open_latch` builds the :class:`drivers.latch.Latch` the config describes, or nothing;
the docking flow then closes it when a dock's faces meet and opens it on ``release``
(docs/firmware.md, "The latch"). A servo latch on the ``[servos]`` port shares the joints'
:class:`~drivers.dynamixel.DynamixelBus` (one lock for both, one port open), so it is built
after the driver and given it.
"""

from __future__ import annotations

from dh2rt.errors import DH2Error
from drivers.base import ModuleDriver
from drivers.latch import Latch
from firmware.config import LatchSpec, ModuleConfig


def open_latch(config: ModuleConfig, driver: ModuleDriver | None = None) -> tuple[Latch | None, str | None]:
    """The latch of ``config`` (None without a ``[latch]``), or (None, why) when it cannot be
    opened: a missing chip, a servo that does not answer, no gpiod. The module runs on
    without it, as it does without servos that cannot be opened, and reports the fault."""
    spec = config.latch
    if spec is None:
        return None, None
    try:
        return _build(spec, config, driver), None
    except DH2Error as exc:
        return None, f"[latch] {spec.kind}: {exc}"


def _build(spec: LatchSpec, config: ModuleConfig, driver: ModuleDriver | None) -> Latch:
    s = spec.settings
    if spec.kind == "recording":
        from drivers.recording import RecordingLatch

        return RecordingLatch(s["timeout_s"])
    if spec.kind == "gpio":
        from drivers.latch import GpioLatch

        return GpioLatch.on_chip(
            s["chip"], s["output_line"], s["input_line"], timeout_s=s["timeout_s"],
            output_active_low=s["output_active_low"], input_active_low=s["input_active_low"],
        )  # fmt: skip
    from drivers.dynamixel import DynamixelBus, DynamixelDriver
    from drivers.latch import ServoLatch

    shared = s["port"] is None and isinstance(driver, DynamixelDriver) and driver.bus.is_open
    if isinstance(driver, DynamixelDriver) and shared:
        bus = driver.bus
    else:
        port = s["port"] or config.servo_port
        assert port is not None  # LatchSpec.from_mapping asks for one
        own = s["port"] is not None
        bus = DynamixelBus(
            port, s["baud"] or config.servo_baud,
            latency_timer_ms=s["latency_ms"] if own else config.servo_latency_ms,
        )  # fmt: skip
    try:
        return ServoLatch(
            bus, s["id"], s["open_deg"], s["closed_deg"], tolerance_deg=s["tolerance_deg"], timeout_s=s["timeout_s"],
            owns_bus=not shared,
        )  # fmt: skip
    except BaseException:
        if not shared:
            bus.close()
        raise
