"""The real devices' wire protocols served over the simulated plant: what tests, benchmarks and
demonstrations talk to instead of hardware.

- `ur`: a Universal Robots controller (RTDE + the script port), `python -m emulators.ur`;
- `natnet`: an OptiTrack NatNet 4.1 server streaming the simulated rig, `python -m emulators.natnet`;
- `serial`: the serial robot controller and laser tracker (pseudo-terminal or TCP);
- `emulated_cell`: all three over one plant, `python -m emulators.emulated_cell`.

Emulators import `dt_kernel`, `sim` and the drivers' protocol codecs (the same bytes as the real
driver speaks); a driver never imports an emulator (tests/unit/test_architecture.py checks it).
"""
