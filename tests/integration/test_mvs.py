"""MVS: synthetic images -> centroids -> triangulation -> cluster pose -> TCP, and the driver."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from drivers.base import CameraRig
from drivers.simulated.camera_images import SimCameraRig
from drivers.mvs import RigModel
from drivers.mvs.calibration import board_points, calibrate_camera
from drivers.mvs.detect import detect_in_rois
from sim.camera_rig import (SimCameraImages, load_rig_config, random_tool_rotation, sample_volume,
                            with_render)
from dt_kernel.errors import ConfigError, StateError

CHI2_3_95 = 7.815  # 95 % quantile of chi^2 with 3 dof


@pytest.fixture(scope="module")
def cfg():
    return load_rig_config()


def _rig(poses, cfg, seed=0, pred_noise=1e-3, predict=True, **kw):
    """A driver following a list of world poses (index in state['k'])."""
    state = {"k": 0}
    rng = np.random.default_rng([seed, 9])
    pred = (lambda: (poses[state["k"]][0], poses[state["k"]][1] + rng.normal(0, pred_noise, 3))) if predict else None
    rig = SimCameraRig(lambda: poses[state["k"]], config=cfg, seed=seed, predicted_pose=pred, **kw)
    rig.configure()
    rig.activate()
    return rig, state


def _poses(n, seed):
    rng = np.random.default_rng([seed, 2])
    return [(random_tool_rotation(rng), p) for p in sample_volume(n, seed)]


def _run(rig, state, poses):
    out = []
    for k in range(len(poses)):
        state["k"] = k
        r = rig.read()
        out.append((r, rig.truth_mvs()))
    return out


def test_config_validated_with_named_errors(cfg, tmp_path):
    assert len(cfg.cameras) == 8 and len(cfg.markers.positions_m) == 5
    assert (cfg.image.width, cfg.image.height) == (2048, 1088)
    bad = tmp_path / "cams.yaml"
    bad.write_text((__import__("pathlib").Path("configs/cameras.yaml").read_text()).replace(
        "spurious_per_image: 0", "spurious_per_image: -2"))
    with pytest.raises(ConfigError, match="render.spurious_per_image"):
        load_rig_config(bad)
    with pytest.raises(ConfigError):
        with_render(cfg, dropped_cameras=["nope"])


def test_rendered_blobs_are_subpixel_accurate(cfg):
    c = with_render(cfg, jitter_px=0.0, exposure_noise=0.0)
    sim = SimCameraImages(c, seed=4)
    errs = []
    for R, p in _poses(4, 4):
        imgs, info = sim.render(R, p)
        for k, img in enumerate(imgs):
            t = info["uv"][k]
            uv, _, ok = detect_in_rois(img, t + 0.7, 12, 8)
            d = np.linalg.norm(t[:, None] - t[None], axis=2) + 1e3 * np.eye(len(t))
            errs.append((uv - t)[ok & (d.min(axis=1) > 16)])  # crowded views are masked by the pipeline
    e = np.concatenate(errs)
    assert len(e) > 120
    assert np.abs(e.mean(axis=0)).max() < 0.01  # unbiased
    assert e.std() < 0.05  # image noise alone; jitter adds the rest of 0.06 px


def test_accuracy_and_coverage_over_the_volume(cfg):
    poses = _poses(50, 11)
    rig, state = _rig(poses, cfg, seed=11)
    res = _run(rig, state, poses)
    assert all(r.ok for r, _ in res)
    e = np.array([r.point - tv for r, tv in res])
    rms = np.sqrt(np.mean(np.sum(e ** 2, axis=1)))
    assert rms < 0.12e-3  # ~0.1 mm 3-D at ~0.06 px pixel noise
    inside = [d @ np.linalg.solve(r.cov, d) < CHI2_3_95 for d, (r, _) in zip(e, res)]
    assert 0.88 <= np.mean(inside) <= 1.0
    q = res[0][0].quality
    assert q["markers_used"] == 5 and q["cameras_used"] == 8 and 0.03 < q["reproj_rms_px"] < 0.1


def test_robust_to_dropout_occlusion_and_reflections(cfg):
    """One camera dropped, two markers occluded, three spurious blobs per image (some next to
    markers): measurements come out or are refused with a reason, never a wrong pose as good."""
    c = with_render(cfg, dropped_cameras=["cam2"], occluded_markers=[1, 3], spurious_per_image=3,
                    spurious_near_marker=0.5, occlusion_probability=0.05)
    poses = _poses(40, 12)
    rig, state = _rig(poses, c, seed=12)
    res = _run(rig, state, poses)
    ok = [(r, tv) for r, tv in res if r.ok]
    assert all(r.refused for r, _ in res if not r.ok)
    assert len(ok) >= 0.8 * len(res)
    for r, tv in ok:
        d = r.point - tv
        assert np.linalg.norm(d) < 1e-3
        assert d @ np.linalg.solve(r.cov, d) < 25.0  # within ~5 sigma of its own uncertainty
        assert r.quality["markers_used"] <= 3 and r.quality["cameras_used"] <= 7


def test_refusals_name_the_reason(cfg):
    poses = _poses(1, 13)
    names = [c.name for c in cfg.cameras]
    rig, state = _rig(poses, with_render(cfg, dropped_cameras=names[:6]), seed=13)
    r = rig.read()
    assert not r.ok and r.point is None and "cameras" in r.refused
    rig, state = _rig(poses, with_render(cfg, occluded_markers=[0, 2, 4]), seed=13)
    r = rig.read()
    assert not r.ok and "markers" in r.refused


def test_bad_prediction_never_gives_a_wrong_pose(cfg):
    """A prediction 40 mm off: the ROI path misses, the epipolar path recovers the cluster."""
    poses = _poses(3, 14)
    rig, state = _rig(poses, cfg, seed=14, pred_noise=0.04)
    for r, tv in _run(rig, state, poses):
        assert (not r.ok and r.refused) or np.linalg.norm(r.point - tv) < 0.5e-3


def test_epipolar_path_without_prediction(cfg):
    poses = _poses(3, 15)
    rig, state = _rig(poses, with_render(cfg, spurious_per_image=3), seed=15, predict=False)
    for r, tv in _run(rig, state, poses):
        assert r.ok, r.refused
        assert np.linalg.norm(r.point - tv) < 0.4e-3


def test_occlusion_callback_hides_a_camera(cfg):
    poses = _poses(1, 16)
    cam0 = np.array(cfg.cameras[0].position_m)
    hide = lambda c, pts: np.full(len(pts), np.allclose(c, cam0, atol=1e-6))  # noqa: E731
    rig, state = _rig(poses, cfg, seed=16, occluded=hide)
    r = rig.read()
    assert r.ok and r.quality["cameras_used"] == 7


def test_driver_lifecycle_protocol_and_determinism(cfg):
    poses = _poses(2, 17)
    rig = SimCameraRig(lambda: poses[0], config=cfg, seed=3)
    assert isinstance(rig, CameraRig)
    with pytest.raises(StateError):
        rig.read()
    rig.configure({"render": {"spurious_per_image": 1}})
    rig.activate()
    a = rig.read()
    rig2 = SimCameraRig(lambda: poses[0], config=cfg, seed=3)
    rig2.configure({"render": {"spurious_per_image": 1}})
    rig2.activate()
    assert np.array_equal(a.point, rig2.read().point)
    with pytest.raises(ConfigError):
        SimCameraRig(lambda: poses[0], config=cfg).configure({"bogus": 1})
    rig.close()
    assert rig.state == "closed"


def test_calibration_from_board_matches_truth(cfg):
    c = with_render(cfg, exposure_noise=0.0)
    sim = SimCameraImages(c, seed=2)
    rows, cols, pitch = 7, 9, 0.06
    B = board_points(rows, cols, pitch)
    rng = np.random.default_rng(1)
    poses = [(np.eye(3), np.array([0.8, -0.2, 0.5]))] + [
        (Rotation.from_euler("xyz", rng.uniform(-25, 25, 3), degrees=True).as_matrix(),
         rng.uniform([0.5, -0.4, 0.2], [1.0, 0.1, 0.8])) for _ in range(9)]
    cams = [0, 3]
    frames = [sim.render(None, None, points=B @ R.T + p)[0] for R, p in poses]
    R0, t0 = poses[0]
    for ci in cams:
        cam = sim.cams[ci]
        cal = calibrate_camera([f[ci] for f in frames], rows, cols, pitch, cam.name)
        assert cal is not None and cal.n_views >= 6
        assert cal.rms_px < 0.15
        assert abs(cal.K[0, 0] / cam.K[0, 0] - 1) < 0.01
        assert np.abs(cal.K[:2, 2] - cam.K[:2, 2]).max() < 20
        Rt, tt = cam.R @ R0, cam.R @ t0 + cam.t  # truth: board-0 frame -> camera
        assert np.linalg.norm(cal.R.T @ cal.t - Rt.T @ tt) < 0.03


def test_processing_model_rejects_bad_calibration():
    with pytest.raises(ConfigError):
        RigModel.build([{"name": "c", "K": np.eye(3), "R": 2 * np.eye(3), "t": [0, 0, 0], "size": [10, 10]}],
                       np.eye(3))
    with pytest.raises(ConfigError):
        RigModel.build([], np.eye(3), processing={"min_markers": 2})


def test_benchmark_smoke():
    from benchmarks.mvs import run

    res = run(n_frames=4, seed=1, min_seconds=0.05)
    for k in ("fps", "baseline_fps", "speedup", "rms_mm"):
        assert k in res and np.isfinite(res[k])
    assert res["speedup"] > 3 and res["rms_mm"] < 0.3
