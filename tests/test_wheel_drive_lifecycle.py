"""WheelDrive's lifecycle: what it does whatever the driver's hooks raise."""
import pytest

from vbnav.drivers.wheels import DriveState, WheelDrive, WheelState


class HalfArmed(WheelDrive):
    """Arms one wheel, then fails with a driver bug (not a DriveError)."""

    def __init__(self):
        super().__init__()
        self.powered = False
        self.stops = 0

    def _configure(self):
        pass

    def _activate(self):
        self.powered = True
        raise ValueError("a driver bug half-way through arming")

    def _write(self, left, right):
        pass

    def _read(self):
        return WheelState(0, (0.0, 0.0), (0.0, 0.0))

    def _stop_wheels(self):
        self.stops += 1
        self.powered = False

    def _release(self):
        pass


def test_enable_stops_what_it_armed_whatever_the_activation_raised():
    """enable() stopped the wheels only on a DriveError: anything else escaped with them armed."""
    d = HalfArmed()
    d.connect()
    with pytest.raises(ValueError, match="half-way"):
        d.enable()
    assert not d.powered and d.stops == 1
    assert d.state is not DriveState.ACTIVE
