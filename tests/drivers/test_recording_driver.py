"""RecordingDriver: the ideal servo that remembers every command."""

from __future__ import annotations

from drivers.base import Health, JointLimits, ModuleDriver
from drivers.recording import RecordingDriver


def test_reports_the_last_target_as_present() -> None:
    driver = RecordingDriver()
    assert driver.read_positions() == (0.0, 0.0)
    driver.set_targets(12.5, -30.0)
    assert driver.read_positions() == (12.5, -30.0)


def test_history_keeps_every_command_in_order() -> None:
    driver = RecordingDriver()
    for angle in (10.0, 20.0, 30.0):
        driver.set_targets(angle, -angle)
    assert driver.history == [(10.0, -10.0), (20.0, -20.0), (30.0, -30.0)]


def test_default_limits_clamp_each_joint() -> None:
    driver = RecordingDriver()
    driver.set_targets(500.0, -500.0)
    assert driver.targets == (90.0, -90.0)


def test_custom_limits_are_per_joint() -> None:
    driver = RecordingDriver(limits=(JointLimits(-10, 10), JointLimits(0, 45)))
    driver.set_targets(-20.0, -20.0)
    assert driver.history[-1] == (-10.0, 0.0)
    assert RecordingDriver().limits == (JointLimits(), JointLimits())  # the class default is kept


def test_torque_switch_and_healthy_by_default() -> None:
    driver = RecordingDriver()
    with driver as entered:
        assert entered is driver and isinstance(driver, ModuleDriver)
        assert driver.torque is True
        driver.set_torque(False)
        assert driver.torque is False
        assert driver.health() == Health() and driver.health().ok
