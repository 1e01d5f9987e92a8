"""Unit factors with names that say which way they convert.

SI inside the code (m, rad, s, kg, degrees C); millimetres in files and reports. A name reads
"what you get per what you have": `x_mm * M_PER_MM` is metres, `x_m * MM_PER_M` is millimetres.
"""
from __future__ import annotations

import math

M_PER_MM = 1e-3  # metres per millimetre: a file value in mm times this is metres
MM_PER_M = 1e3  # millimetres per metre: a value in m times this is millimetres
RAD_PER_DEG = math.pi / 180.0
DEG_PER_RAD = 180.0 / math.pi
URAD_PER_RAD = 1e6

AXES = ("x", "y", "z")  # Cartesian axes, in the order of every (..., 3) array
