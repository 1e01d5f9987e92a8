"""The physical world in software: simulated cobot plant, instruments, controller emulator.

Knows nothing of the model side (never imports drivers or dt_runtime).
"""
