"""MVS throughput: eight 2048x1088 images -> TCP, frame sets per second on one core.

Ours: regions of interest around the twin's predicted markers (`MarkerTracker.measure` with a
predicted pose). Baseline, same run and same frames: naive full-frame threshold + connected
components per image (binary centroids), nearest blob to each predicted marker, then the same
triangulation and cluster fit. Frames are rendered once beforehand; rendering is not timed.

`python -m benchmarks.mvs [--json] [--frames N] [--seed S]`; JSON keys: fps, baseline_fps,
speedup, rms_mm (3-D TCP error of ours against the truth), baseline_rms_mm, n_frames, refused,
machine (the reference workload's time, load, CPU: `benchmarks._common.Machine`), relative (fps
times the reference workload's time: frame sets per reference workload). `--load-core`: while
another process keeps one core busy.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # one core

import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from drivers.simulated.camera_images import SimCameraRig  # noqa: E402
from drivers.mvs.detect import baseline_detect  # noqa: E402
from drivers.mvs.pipeline import MarkerTracker, _distort  # noqa: E402
from sim.camera_rig import random_tool_rotation, sample_volume  # noqa: E402
from benchmarks._common import Machine, busy_core, cli, emit  # noqa: E402


def _baseline_measure(tr: MarkerTracker, images, pred):
    """Naive pipeline: full-frame threshold + connected components, nearest blob, same backend."""
    M, C = len(tr.model.markers), len(tr.stack)
    X = tr.model.markers @ pred[0].T + pred[1]
    _, Xc = tr.stack.project(X)
    pp = _distort(tr.K, tr.D, Xc[..., :2] / Xc[..., 2:3])
    uv = np.zeros((M, C, 2))
    mask = np.zeros((M, C), bool)
    for c, img in enumerate(images):
        if img is None:
            continue
        blobs = baseline_detect(img)
        if len(blobs) == 0:
            continue
        d = np.linalg.norm(pp[:, c, None, :] - blobs[None], axis=2)
        j = np.argmin(d, axis=1)
        hit = d[np.arange(M), j] < tr.p.roi_half_px
        uv[hit, c] = blobs[j[hit]]
        mask[:, c] = hit
        if hit.any():
            uv[:, c] = cv2.undistortPoints(uv[:, c].reshape(-1, 1, 2), tr.K[c], tr.D[c], P=tr.K[c]).reshape(-1, 2)
    sig = np.full((M, C), tr.p.centroid_sigma_px)
    return tr.measure_observations(uv, sig, mask)


def run(n_frames: int = 40, seed: int = 0, min_seconds: float = 1.0) -> dict:
    cv2.setNumThreads(1)
    rng = np.random.default_rng([seed, 1])
    poses = [(random_tool_rotation(rng), p) for p in sample_volume(n_frames, seed)]
    state = {"k": 0}
    rig = SimCameraRig(lambda: poses[state["k"]], seed=seed)
    frames, truths, preds = [], [], []
    for k, (R, p) in enumerate(poses):
        state["k"] = k
        imgs, _ = rig.renderer.render(R, p)
        frames.append(imgs)
        truths.append(rig.truth_mvs())
        # The twin's prediction: the actual pose off by ~1 mm (its residual positioning error).
        preds.append(rig.world_to_mvs_nominal(R, p + rng.normal(0, 1e-3, 3)))
    tr = rig.tracker

    def timed(fn):
        reps, t0, out = 0, time.perf_counter(), None
        while True:
            out = [fn(tr, f, pr) for f, pr in zip(frames, preds)]
            reps += 1
            if time.perf_counter() - t0 >= min_seconds:
                break
        return reps * len(frames) / (time.perf_counter() - t0), out

    fps, ours = timed(lambda t, f, pr: t.measure(f, pr))
    base_fps, base = timed(_baseline_measure)

    def rms(res):
        e = [m.tcp - tv for m, tv in zip(res, truths) if m.ok]
        return float(np.sqrt(np.mean(np.sum(np.square(e), axis=1))) * 1e3) if e else float("nan")

    return {"fps": round(fps, 1), "baseline_fps": round(base_fps, 1), "speedup": round(fps / base_fps, 2),
            "rms_mm": round(rms(ours), 4), "baseline_rms_mm": round(rms(base), 4), "n_frames": n_frames,
            "refused": sum(not m.ok for m in ours), "cameras": len(tr.stack),
            "image": list(tr.model.cameras[0].size)}


def main(argv=None) -> int:
    a = cli(__doc__.splitlines()[0], argv, frames=40, seed=0, load_core=False)
    with busy_core(a.load_core) as loaded, Machine() as m:
        r = run(a.frames, a.seed)
    r["machine"] = m.report() | {"one_core_loaded": loaded}
    r["relative"] = m.relative(rates_hz={"fps": r["fps"], "baseline_fps": r["baseline_fps"]})
    emit(r, a.json, "MVS: eight frames -> TCP, ours vs the full-frame baseline")
    return 0


if __name__ == "__main__":
    sys.exit(main())
