"""Camera calibration from a dot board recorded by the rig (OpenCV `calibrateCamera`).

The board is a `rows` x `cols` grid of retro-reflective dots at `pitch` (m) plus one key dot at
the centre of the first cell, (0.5, 0.5) pitch, which fixes the board's orientation. In each
image, the blobs are found full frame, the grid's four hull corners give a homography to grid
coordinates, and the key dot picks the one of the eight corner assignments that is right;
a homography on all dots then labels every blob. Per camera, `cv2.calibrateCamera` estimates
K, the distortion (k1, k2, p1, p2; k3 fixed at 0) and the board poses; the extrinsics are
expressed in the frame of the first board pose (the calibration frame).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from drivers.mvs.detect import detect_full_frame


def board_points(rows: int = 7, cols: int = 9, pitch: float = 0.04) -> np.ndarray:
    """Dot centres in the board frame (m): the grid row by row, then the key dot (last).

    Parameters
    ----------
    rows, cols : int
        The grid's size in dots.
    pitch : float
        Dot spacing (m).

    Returns
    -------
    ndarray
        (rows*cols + 1, 3) m.
    """
    g = np.array([[c * pitch, r * pitch, 0.0] for r in range(rows) for c in range(cols)])
    return np.vstack([g, [0.5 * pitch, 0.5 * pitch, 0.0]])


def order_grid(uv: np.ndarray, rows: int, cols: int, tol: float = 0.25) -> np.ndarray | None:
    """Label image blobs with grid indices, using the four hull corners and the key dot.

    Parameters
    ----------
    uv : ndarray
        (n, 2) px, blob centroids; n must be rows*cols + 1 (the grid and the key dot).
    rows, cols : int
        The grid's size in dots.
    tol : float
        Largest distance from a grid node or the key dot's position, in grid pitches.

    Returns
    -------
    ndarray or None
        (rows*cols, 2) px in board order, or None when the grid is not found complete and
        unambiguous.
    """
    if len(uv) != rows * cols + 1:
        return None
    pts = uv.astype(np.float32)
    hull = cv2.convexHull(pts)
    peri = cv2.arcLength(hull, True)
    quad = cv2.approxPolyDP(hull, 0.03 * peri, True).reshape(-1, 2)
    if len(quad) != 4:
        return None
    ideal = np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], np.float32)
    best = None
    for shift, flip in itertools.product(range(4), (False, True)):
        q = np.roll(quad[::-1] if flip else quad, shift, axis=0).astype(np.float32)
        H = cv2.getPerspectiveTransform(q, ideal)
        g = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), H).reshape(-1, 2)
        key = np.linalg.norm(g - 0.5, axis=1)
        k = int(np.argmin(key))
        if key[k] > tol:
            continue
        rest = np.delete(g, k, axis=0)
        idx = np.rint(rest)
        if np.abs(rest - idx).max() > tol:
            continue
        ii = (idx[:, 1] * cols + idx[:, 0]).astype(int)
        if ii.min() < 0 or ii.max() >= rows * cols or len(set(ii)) != rows * cols:
            continue
        out = np.zeros((rows * cols, 2))
        out[ii] = np.delete(uv, k, axis=0)
        if best is not None:
            return None  # ambiguous
        best = out
    return best


@dataclass(frozen=True)
class CameraCalibration:
    """One camera's calibration: ``K`` (3, 3) px, ``dist`` (k1, k2, p1, p2, k3), ``R`` and ``t`` (m)
    from the calibration frame (the first board pose) to the camera, the reprojection ``rms_px`` and
    the number of board views used.
    """
    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray  # calibration frame (first board pose) -> camera
    t: np.ndarray
    rms_px: float
    n_views: int


def calibrate_camera(images: list[np.ndarray | None], rows: int, cols: int, pitch: float,
                     name: str = "cam", window_half_px: int = 5) -> CameraCalibration | None:
    """Calibrate one camera from its images of the board (image 0 = the calibration frame).

    Parameters
    ----------
    images : list of ndarray or None
        8-bit images; None for a view the camera did not record.
    rows, cols : int
        The grid's size in dots.
    pitch : float
        Dot spacing (m).
    name : str
        The camera's name.
    window_half_px : int
        Half-size of the centroid window (px).

    Returns
    -------
    CameraCalibration or None
        None when the board is not found in image 0 or in fewer than 4 images.
    """
    obj = board_points(rows, cols, pitch)[:-1].astype(np.float32)
    objs: list[np.ndarray] = []
    imgs: list[np.ndarray] = []
    first: int | None = None
    size: tuple[int, int] | None = None
    for k, img in enumerate(images):
        if img is None:
            continue
        size = (img.shape[1], img.shape[0])
        uv, _, ok = detect_full_frame(img, window_half_px)
        ordered = order_grid(uv[ok], rows, cols)
        if ordered is None:
            continue
        if k == 0:
            first = len(objs)
        objs.append(obj)
        imgs.append(ordered.astype(np.float32).reshape(-1, 1, 2))
    if first is None or len(objs) < 4:
        return None
    assert size is not None  # set from every image read, and image 0 was read (first is not None)
    flags = cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objs, imgs, size, None, None, flags=flags)
    R = cv2.Rodrigues(rvecs[first])[0]
    return CameraCalibration(name, K, dist.reshape(-1)[:5], R, tvecs[first].reshape(3), float(rms), len(objs))
