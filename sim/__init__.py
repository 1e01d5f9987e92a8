"""The physical world in software: the simulated cobot plant with switchable error effects,
the laser tracker, the point MVS stand-in, the camera-rig image simulator and the servo follower of
a streamed path (servo).

Knows nothing of the model side: imports only dt_kernel, never drivers or dt_runtime. The
devices' emulators, which serve the real wire protocols over this plant, are in emulators/.
"""
