"""Hardware-abstraction layer: robot controller, laser tracker and camera rig drivers."""
