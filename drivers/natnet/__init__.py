"""OptiTrack NatNet: the paper's camera system, reached through its public streaming protocol.

- `protocol`: pack/unpack of the NatNet 4.1 messages used (pure functions).
- `emulator`: a NatNet server streaming frames of data from the simulated camera rig, with
  faults injected through its config (`python -m drivers.natnet.emulator --help`).
- `driver`: `NatNetRig`, a CameraRig turning the frames into the MVS measurement of the TCP
  (the cluster fit of drivers.mvs), with quality record and refusals.
"""
