"""OptiTrack NatNet: the paper's camera system, reached through its public streaming protocol.

- `protocol`: pack/unpack of the NatNet 4.1 messages used (pure functions).
- `driver`: `NatNetRig`, a CameraRig turning the frames into the MVS measurement of the TCP
  (the cluster fit of drivers.mvs), with quality record and refusals.

The NatNet server that streams the simulated rig is an emulator: `emulators.natnet`
(`python -m emulators.natnet --help`).
"""
