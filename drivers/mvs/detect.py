"""Sub-pixel blob centroids: in regions of interest around predicted markers, or full frame.

Both paths end in the same vectorised intensity-weighted centroid (`centroid_windows`): a
(2w+1)^2 window around each blob's peak, background-subtracted with a relative threshold, so
the centroid of a symmetric blob is unbiased. Each centroid carries its image-noise standard
deviation (sigma_c^2 = sigma_n^2 sum (x - xc)^2 / (sum I)^2) and a shape flag that rejects
blobs merged with a neighbour (weight on the window edge, or strongly elongated).
"""
from __future__ import annotations

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

REL_THRESHOLD = 0.10  # fraction of the background-subtracted peak kept in the centroid
MIN_PEAK_DN = 25.0  # a blob must rise this much above the background


def _gather(img: np.ndarray, cu: np.ndarray, cv: np.ndarray, h: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Square (2h+1)^2 patches of `img` centred at integer (cu, cv), shifted to lie inside the image.

    Returns the patches (n, S, S) as float32 and their top-left corners (x0, y0)."""
    H, W = img.shape
    x0 = np.clip(cu - h, 0, W - 2 * h - 1)
    y0 = np.clip(cv - h, 0, H - 2 * h - 1)
    ar = np.arange(2 * h + 1)
    rows = (y0[:, None] + ar)[:, :, None]
    cols = (x0[:, None] + ar)[:, None, :]
    return img[rows, cols].astype(np.float32), x0, y0


def _centroid_patches(win: np.ndarray, x0: np.ndarray, y0: np.ndarray):
    """Centroids of pre-gathered (n,S,S) float windows with top-left corners (x0, y0).

    Background and noise come from the darkest side of the window border (a neighbouring blob
    leaking into one side does not raise them). The image-noise centroid sigma per axis,
    sigma_n sqrt(sum_{w>0} (x - xc)^2) / sum w, is evaluated for the N thresholded pixels as
    a disc (sum (x - xc)^2 = N^2 / 4 pi)."""
    n, S = win.shape[0], win.shape[1]
    sides = np.stack([win[:, 0, :], win[:, -1, :], win[:, :, 0], win[:, :, -1]], axis=1)  # (n,4,S)
    means = sides.mean(axis=2)
    j = np.argmin(means, axis=1)
    background = means[np.arange(n), j]
    noise = sides[np.arange(n), j].std(axis=1) + 0.5
    peak = win.reshape(n, -1).max(axis=1) - background
    thr = background + np.maximum(REL_THRESHOLD * peak, 3.0 * noise)
    wt = np.maximum(win - thr[:, None, None], 0.0)
    colw, roww = wt.sum(axis=1), wt.sum(axis=2)
    tot = colw.sum(axis=1)
    ar = np.arange(S, dtype=np.float32)
    safe = np.where(tot > 0, tot, 1.0)
    xc, yc = (colw @ ar) / safe, (roww @ ar) / safe
    # Second moments and edge weight: a blob merged with a neighbour is wider or leaks out.
    dx2 = (colw @ (ar * ar)) / safe - xc * xc
    dy2 = (roww @ (ar * ar)) / safe - yc * yc
    edge = colw[:, 0] + colw[:, -1] + roww[:, 0] + roww[:, -1]
    n_px = np.count_nonzero(wt.reshape(n, -1), axis=1)
    sig_img = noise * n_px / (np.sqrt(4 * np.pi) * safe)
    ratio = np.maximum(dx2, dy2) / np.maximum(np.minimum(dx2, dy2), 1e-6)
    ok = (peak >= MIN_PEAK_DN) & (tot > 0) & (edge <= 0.02 * tot) & (ratio < 1.5)
    return np.c_[x0 + xc, y0 + yc].astype(np.float64), sig_img.astype(np.float64), ok


def centroid_windows(img: np.ndarray, peaks_xy: np.ndarray, w: int):
    """Intensity-weighted centroids of the blobs whose peak pixels are given.

    Parameters
    ----------
    img : ndarray
        (H, W) 8-bit image.
    peaks_xy : ndarray
        (n, 2) int, the peak pixels (x, y).
    w : int
        Half-size of the (2w+1)^2 centroid window (px).

    Returns
    -------
    uv : ndarray
        (n, 2) px.
    sigma_img : ndarray
        (n,) px, the image-noise standard deviation of each centroid.
    ok : ndarray
        (n,) bool: bright enough and blob-shaped (not merged with a neighbour).
    """
    if len(peaks_xy) == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
    win, x0, y0 = _gather(img, peaks_xy[:, 0].astype(np.int64), peaks_xy[:, 1].astype(np.int64), w)
    return _centroid_patches(win, x0, y0)


def detect_in_rois(img: np.ndarray, centres: np.ndarray, roi_half: int, w: int, focus_px: float = 6.0):
    """One blob per ROI of one image; see ``detect_in_rois_multi``.

    Parameters
    ----------
    img : ndarray
        (H, W) 8-bit image.
    centres : ndarray
        (M, 2) px, the predicted marker positions (image pixels).
    roi_half : int
        Half-size of the ROI (px).
    w : int
        Half-size of the centroid window (px).
    focus_px : float
        Standard deviation of the Gaussian focus on the predicted centre (px).

    Returns
    -------
    uv : ndarray
        (M, 2) px.
    sigma_img : ndarray
        (M,) px.
    ok : ndarray
        (M,) bool.
    """
    uv, sig, ok = detect_in_rois_multi([img], np.asarray(centres, float)[:, None, :], roi_half, w, focus_px)
    return uv[:, 0], sig[:, 0], ok[:, 0]


def detect_in_rois_multi(images, centres: np.ndarray, roi_half: int, w: int, focus_px: float = 6.0):
    """One blob per ROI, for M predicted centres in C images.

    The peak is the argmax, over the (2 roi_half + 1)^2 ROI, of the intensity times a Gaussian
    focus on the predicted centre, so a spurious reflection elsewhere in the ROI does not win
    over the marker; the centroid is then taken in a (2w+1)^2 window around that peak. One
    gather per camera (ROI plus window margin); everything else is one batch over all ROIs of
    all cameras.

    Parameters
    ----------
    images : sequence of ndarray or None
        C 8-bit images; None for a camera without a frame.
    centres : ndarray
        (M, C, 2) px, the predicted marker positions (image pixels; non-finite: not visible).
    roi_half : int
        Half-size of the ROI (px).
    w : int
        Half-size of the centroid window (px).
    focus_px : float
        Standard deviation of the Gaussian focus (px).

    Returns
    -------
    uv : ndarray
        (M, C, 2) px.
    sigma_img : ndarray
        (M, C) px.
    ok : ndarray
        (M, C) bool; False where there is no frame, the centre is outside the image or the blob
        fails the shape check.
    """
    M, C = centres.shape[:2]
    uv = np.zeros((M, C, 2))
    sig = np.ones((M, C))
    ok = np.zeros((M, C), bool)
    cams = [c for c, im in enumerate(images) if im is not None]
    if not cams or M == 0:
        return uv, sig, ok
    h = roi_half + w  # gather the ROI with the centroid window's margin
    S, Sr, Sw = 2 * h + 1, 2 * roi_half + 1, 2 * w + 1
    cen = centres[:, cams].transpose(1, 0, 2).reshape(-1, 2)  # (len(cams)*M, 2)
    fin = np.all(np.isfinite(cen), axis=1)
    cen = np.where(fin[:, None], cen, -1e6)
    c = np.rint(cen).astype(np.int64)
    ar = np.arange(S)
    patches, px0, py0, inside_k = [], [], [], []
    for k, cam in enumerate(cams):
        img = images[cam]
        H, W = img.shape
        cc = c[k * M:(k + 1) * M]
        inside_k.append((cc[:, 0] >= 0) & (cc[:, 0] < W) & (cc[:, 1] >= 0) & (cc[:, 1] < H))
        x0 = np.minimum(np.maximum(cc[:, 0] - h, 0), W - S)
        y0 = np.minimum(np.maximum(cc[:, 1] - h, 0), H - S)
        patches.append(img[(y0[:, None] + ar)[:, :, None], (x0[:, None] + ar)[:, None, :]])
        px0.append(x0)
        py0.append(y0)
    patch = np.concatenate(patches)
    x0, y0, inside = np.concatenate(px0), np.concatenate(py0), np.concatenate(inside_k)
    n = len(patch)
    # Peak search in the inner ROI (offset w inside the gathered patch).
    inner = patch[:, w:w + Sr, w:w + Sr].astype(np.float32)
    ai = np.arange(Sr)
    du = ai[None, :] + w - (cen[:, 0] - x0)[:, None]
    dv = ai[None, :] + w - (cen[:, 1] - y0)[:, None]
    fu = np.exp(-0.5 * du ** 2 / focus_px ** 2).astype(np.float32)
    fv = np.exp(-0.5 * dv ** 2 / focus_px ** 2).astype(np.float32)
    k = np.argmax((inner * fv[:, :, None] * fu[:, None, :]).reshape(n, -1), axis=1)
    py, px = np.divmod(k, Sr)  # peak at patch (py + w, px + w): window starts at (py, px)
    win = sliding_window_view(patch, (Sw, Sw), axis=(1, 2))[np.arange(n), py, px].astype(np.float32)
    u, s, good = _centroid_patches(win, x0 + px, y0 + py)
    good &= inside & fin
    uv[:, cams] = u.reshape(len(cams), M, 2).transpose(1, 0, 2)
    sig[:, cams] = s.reshape(len(cams), M).T
    ok[:, cams] = good.reshape(len(cams), M).T
    return uv, sig, ok


def detect_full_frame(img: np.ndarray, w: int, threshold_dn: float = 40.0, min_area: int = 3):
    """All blobs of a full image: threshold + connected components, then the sub-pixel centroid.

    Parameters
    ----------
    img : ndarray
        (H, W) 8-bit image.
    w : int
        Half-size of the centroid window (px).
    threshold_dn : float
        Binary threshold (digital numbers).
    min_area : int
        Smallest component kept (px).

    Returns
    -------
    uv : ndarray
        (n, 2) px.
    sigma_img : ndarray
        (n,) px.
    ok : ndarray
        (n,) bool.
    """
    _, binary = cv2.threshold(img, threshold_dn, 255, cv2.THRESH_BINARY)
    n, _, stats, cents = cv2.connectedComponentsWithStats(binary, connectivity=8)
    keep = stats[1:, cv2.CC_STAT_AREA] >= min_area
    if not np.any(keep):
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool)
    peaks = np.rint(cents[1:][keep]).astype(np.int64)
    # Move each seed to the brightest pixel of a small neighbourhood (its peak).
    p3, x0, y0 = _gather(img, peaks[:, 0], peaks[:, 1], 2)
    k = np.argmax(p3.reshape(len(peaks), -1), axis=1)
    py, px = np.divmod(k, 5)
    return centroid_windows(img, np.c_[x0 + px, y0 + py], w)


def baseline_detect(img: np.ndarray, threshold_dn: float = 40.0, min_area: int = 3) -> np.ndarray:
    """The naive baseline: full-frame threshold + connected components, binary centroids.

    Parameters
    ----------
    img : ndarray
        (H, W) 8-bit image.
    threshold_dn : float
        Binary threshold (digital numbers).
    min_area : int
        Smallest component kept (px).

    Returns
    -------
    ndarray
        (n, 2) px.
    """
    _, binary = cv2.threshold(img, threshold_dn, 255, cv2.THRESH_BINARY)
    n, _, stats, cents = cv2.connectedComponentsWithStats(binary, connectivity=8)
    return cents[1:][stats[1:, cv2.CC_STAT_AREA] >= min_area]
