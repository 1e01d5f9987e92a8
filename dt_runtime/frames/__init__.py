"""Frames: rigid registration (Kabsch/Umeyama, the paper's three-line frame, residuals and
reproducibility, Eqs. 4-7, 12) and the twin-side kinematic chain (URDF or DH).
"""
