"""Synthetic stand-in for the paper's DOE (Sect. 2.2): swap `doe_dataset` for simulator data later;
and the real UR10 laser-tracker data shipped with the project (Fraunhofer IPA, Series A).

Positions in metres, speed in m/s, errors in metres (SI inside the code: docs/cli.md, Conventions)."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from dt_runtime.common.paths import CONFIGS, DATA

UR10_SERIES_A = DATA / "ipa_ur10" / "Series_A" / "measurements_grid.csv"
UR10_MAPPING = CONFIGS / "import" / "ur10.yaml"
UR10_ROBOT = CONFIGS / "robots" / "ur10.yaml"

SPEED_MAX = 1.0  # m/s
ORIGIN = np.array([0.35, -0.5, 0.25])  # corner of the ~1 m x 0.7 m x 0.7 m volume, robot frame


def error_field(X: np.ndarray) -> np.ndarray:
    """Smooth position-dependent errors (n, 3) in metres, ~0.8/0.5/0.3 mm std, plus a small speed term."""
    p = (X[:, :3] - ORIGIN) / np.array([1.0, 0.7, 0.7])  # 0..1 in the volume
    x, y, z, v = p[:, 0], p[:, 1], p[:, 2], X[:, 3] / SPEED_MAX
    ex = 0.9 * np.sin(2.1 * x + 0.4) + 0.5 * np.cos(2.7 * y - 0.3 * z) + 0.4 * np.sin(3.0 * z + x) + 0.08 * v
    ey = 0.6 * np.sin(2.5 * y + 1.0) + 0.35 * np.cos(1.8 * x + 2.2 * z) + 0.06 * v * (x - 0.5)
    ez = 0.35 * np.sin(2.0 * z + 0.5 * x) + 0.2 * np.cos(2.6 * x - 1.0) + 0.15 * np.sin(3.0 * y) + 0.05 * v
    return 1e-3 * np.column_stack([ex * 0.8 / 0.465, ey * 0.5 / 0.389, ez * 0.3 / 0.101])


def doe_points() -> np.ndarray:
    """62 target points (m): three rectangles in planes 350 mm apart with 9, 13, 26 points on their
    sides and diagonals, plus 14 points on the lines joining their vertexes (paper Fig. 5)."""
    halves = [(0.2, 0.15), (0.3, 0.25), (0.5, 0.35)]
    counts = [9, 13, 26]
    centre = ORIGIN[:2] + np.array([0.5, 0.35])
    pts, verts = [], []
    for k, ((a, b), n) in enumerate(zip(halves, counts)):
        zk = ORIGIN[2] + 0.35 * k
        V = centre + np.array([[-a, -b], [a, -b], [a, b], [-a, b]])
        verts.append(np.column_stack([V, np.full(4, zk)]))
        loop = np.vstack([V, V[:1]])
        seg = np.linalg.norm(np.diff(loop, axis=0), axis=1)
        s = np.linspace(0, seg.sum(), n - 1, endpoint=False)  # n-1 on the sides + the centre (diagonals)
        cum = np.r_[0, np.cumsum(seg)]
        i = np.searchsorted(cum, s, side="right") - 1
        t = (s - cum[i]) / seg[i]
        xy = loop[i] + t[:, None] * (loop[i + 1] - loop[i])
        pts.append(np.column_stack([np.vstack([xy, centre]), np.full(n, zk)]))
    lines = []
    for k in range(2):
        for j in range(4):
            lines.append((verts[k][j], verts[k + 1][j]))
    fr = [0.33, 0.66]
    extra = [a + f * (b - a) for a, b in lines for f in fr][:14]
    return np.vstack(pts + [np.array(extra)])


def doe_dataset(seed: int = 0, reps: int = 9, speeds=(0.3, 0.6, 0.9), noise=1e-5):
    """Training set: 62 points x speeds x reps rows; X (n, 4) = [x, y, z, v], Y (n, 3) errors (m)."""
    rng = np.random.default_rng(seed)
    P = doe_points()
    X = np.array([[*p, s * SPEED_MAX] for p in P for s in speeds for _ in range(reps)])
    return X, error_field(X) + rng.normal(0, noise, (len(X), 3))


def validation_dataset(seed: int = 1, n_points: int = 14, speeds=(0.8, 0.4), reps: int = 5, noise=1e-5):
    """Held-out set: new points inside the DOE volume x 2 speeds x 5 replications."""
    rng = np.random.default_rng(seed)
    lo, hi = ORIGIN + [0.1, 0.1, 0.05], ORIGIN + [0.9, 0.6, 0.65]
    P = rng.uniform(lo, hi, (n_points, 3))
    X = np.array([[*p, s * SPEED_MAX] for p in P for s in speeds for _ in range(reps)])
    return X, error_field(X) + rng.normal(0, noise, (len(X), 3))


def scattered_dataset(n: int, seed: int = 0, noise=1e-5):
    """n distinct inputs scattered in the volume with continuous speeds (for scale tests)."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(ORIGIN, ORIGIN + [1.0, 0.7, 0.7], (n, 3)), rng.uniform(0.2, 1.0, n)])
    return X, error_field(X) + rng.normal(0, noise, (n, 3))


# --- UR10 (IPA) laser-tracker data -----------------------------------------------------------
@functools.lru_cache(maxsize=4)
def ur10_dataset(path: str | Path = UR10_SERIES_A):
    """A UR10 file (default Series A: 619 grid points visited ~19 times each, 11,911 rows) read
    through configs/import/ur10.yaml: registered, SI, rows in time order, `point_id` per grid point."""
    from dt_runtime.measurements.importer import import_file

    return import_file(Path(path), UR10_MAPPING)[0]


def ur10_subset_file(n: int, out: str | Path, seed: int = 0, path: str | Path = UR10_SERIES_A) -> Path:
    """Write a seeded random subset of n data rows of a UR10 file (header kept, file order kept)
    to `out`, for `dt fit` on fewer rows. Returns `out`."""
    lines = Path(path).read_bytes().splitlines()
    header, rows = lines[0], [r for r in lines[1:] if r.strip()]
    keep = np.sort(np.random.default_rng(seed).choice(len(rows), min(n, len(rows)), replace=False))
    out = Path(out)
    out.write_bytes(b"\n".join([header] + [rows[i] for i in keep]) + b"\n")
    return out


def point_split(point_id: np.ndarray, holdout: float = 0.3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (sorted, so time order is kept) of training and held-out rows: a seeded
    `holdout` fraction of the distinct points is held out whole (every repetition of a point
    is on one side, so a model cannot win by remembering a point)."""
    pts = np.unique(point_id)
    test_pts = np.random.default_rng(seed).choice(pts, int(round(holdout * len(pts))), replace=False)
    test = np.isin(point_id, test_pts)
    return np.flatnonzero(~test), np.flatnonzero(test)
