"""The serial devices' emulators (`devices`): a robot controller and a laser tracker serving
`drivers.serial.protocol` on a pseudo-terminal or a loopback TCP port."""
from emulators.serial.devices import FAULT_KINDS, ControllerEmulator, Faults, TrackerEmulator

__all__ = ["FAULT_KINDS", "ControllerEmulator", "Faults", "TrackerEmulator"]
