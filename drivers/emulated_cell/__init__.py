"""The UR, NatNet and serial tracker emulators over one simulated plant: `python -m drivers.emulated_cell`."""
from drivers.emulated_cell.cell import EmulatedCell, control, main

__all__ = ["EmulatedCell", "control", "main"]
