"""A Universal Robots controller on loopback (`controller.UrEmulator`: RTDE and the script port over
the plant; `motion`: the emulated arm's motion profile). `python -m emulators.ur --help`."""
from emulators.ur.controller import UrEmulator, UrFaults

__all__ = ["UrEmulator", "UrFaults"]
