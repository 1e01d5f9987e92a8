"""Multi-camera marker tracking (MVS processing) with OpenCV.

From the rig's 8-bit images to the TCP/SMR point with its covariance:

- `detect`: sub-pixel blob centroids (ROI around predicted markers, or full frame).
- `camera`: the calibrated camera model the rig knows (intrinsics, distortion, extrinsics in
  the MVS frame) and undistortion.
- `triangulate`: N-view triangulation (linear DLT, then Gauss-Newton on the reprojection error)
  with per-view outlier rejection, and epipolar correspondence when no prediction is given.
- `cluster`: rigid fit of the marker cluster (Kabsch, then pose refinement on the pixels) with
  the pose covariance propagated from the pixel noise; marker identification from 3-D points.
- `pipeline`: `MarkerTracker.measure(images, predicted_pose=None) -> MvsMeasurement`, with a
  quality flag and refusal reasons.
- `calibration`: camera calibration from a dot board recorded by the rig.

This package never imports sim/: the calibration reaches it as plain data (dicts/arrays).
"""
from drivers.mvs.camera import Camera, RigModel
from drivers.mvs.pipeline import MarkerTracker, MvsMeasurement

__all__ = ["Camera", "RigModel", "MarkerTracker", "MvsMeasurement"]
