"""An OptiTrack NatNet 4.1 server (`server.NatNetEmulator`) streaming the markers of the simulated
camera rig (`rig_source.SimRigMarkers`), faults injected through its config.
`python -m emulators.natnet --help`."""
from emulators.natnet.rig_source import SimRigMarkers
from emulators.natnet.server import NatNetEmulator

__all__ = ["NatNetEmulator", "SimRigMarkers"]
