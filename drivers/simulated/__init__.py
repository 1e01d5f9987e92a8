"""Simulated drivers: real implementations of the driver protocols over the PyBullet cell
(`devices`: robot, tracker, point-noise camera stand-in, the shared `SimWorld`) and the
image camera rig whose frames go through the MVS processing (`camera_images`).
"""
