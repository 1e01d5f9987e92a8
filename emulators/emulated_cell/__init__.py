"""The UR, NatNet and serial tracker emulators over one simulated plant: `python -m emulators.emulated_cell`."""
from emulators.emulated_cell.cell import EmulatedCell, control, main

__all__ = ["EmulatedCell", "control", "main"]
