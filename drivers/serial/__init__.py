"""Devices on a serial line: the checksummed, sequenced line protocol (`protocol`), the robot
controller (`controller`) and laser-tracker (`tracker`) drivers that speak it; the emulators
that serve it on a pseudo-terminal over the simulated plant are `emulators.serial`. As with pyserial's URL
handlers, the same driver code and tests run on the emulator and on hardware.
"""
